"""Export a generated dataset for SPIN/HMR-style loaders (``.npz``), as COCO keypoints (JSON) or,
for a video dataset (``docs/video.md``), as one BEDLAM/GVHMR-style ``.npz`` per sequence.

    synth export DATASET --format spin --out OUT    # or: export("data/val", "coco", "exports/val")

Every format copies every sample's ``rgb.png`` unchanged to ``OUT/images/<key>.png``; ``spin`` and
``coco`` hold one entry per person instance with at least ``min_pixels`` visible mask pixels,
``sequences`` every person of a sequence in every frame. Pixel coordinates are
written as they are in the dataset: continuous OpenCV coordinates with pixel centres at integer
+ 0.5 (pixel ``(u, v)`` covers ``[u, u + 1) x [v, v + 1)``); COCO's own convention is ambiguous, so
subtract 0.5 where a tool puts pixel centres at integers.

``spin`` writes ``OUT/blsm_synth.npz`` (N persons; load with ``allow_pickle=False``):

================  ==============  ===================================================================
``imgname``       (N,) str        ``images/<key>.png``, relative to ``OUT``
``center``        (N, 2)          centre of the visible ``box`` (``box_full`` when none), pixels
``scale``         (N,)            ``scale_factor * max(w, h) / 200``: SPIN's preprocessing (1.2 box)
``part``          (N, 24, 3)      SPIN's 24 keypoints (:data:`SPIN_KEYPOINTS`): x, y and SPIN's
                                  confidence: 1 for every keypoint inside the image, occluded or not
                                  (SPIN's COCO preprocessing: v > 0), 0 outside; keypoints we do
                                  not have are 0 with confidence 0
``visible``       (N, 24) bool    the keypoint is inside the image and seen (not occluded by the
                                  person or anything else; :mod:`synth.dataset.format`)
``S``             (N, 24, 4)      the same keypoints in camera metres (not centred) and confidence
``pose``          (N, 47)         BLSM unconstrained pose x; ``angles`` (N, 47) radians
``bone``          (N, Kb)         bone coefficients; ``shape`` (N, Ks) shape coefficients
``global_orient`` (N, 3)          axis-angle in the camera frame, ``R R_global``
``transl_cam``    (N, 3)          pelvis in camera metres
``K``             (N, 3, 3)       camera intrinsics of the image
``has_smpl``      (N,)            0 (the bodies are BLSM, not SMPL); ``has_blsm`` (N,) 1
================  ==============  ===================================================================

``sequences`` writes ``OUT/<sequence:06d>.npz`` per sequence (``T`` frames, ``P`` people in track
order, ``K`` keypoints; load with ``allow_pickle=False``) and, last, ``OUT/sequences.json``, the
list of those files with ``frames``, ``fps`` and ``contact_names``. World arrays are in the
sequence's one world frame (metres, Y up, ground ``y = 0``); velocities and contact are the
generator's (``docs/video.md``):

====================  ==============  =================================================================
``imgname``           (T,) str        ``images/<key>.png`` of each frame, relative to ``OUT``
``frame``, ``time``   (T,), (T,)      frame numbers ``0 .. T-1`` and seconds from the start
``fps``               ()              frames per second
``image_size``        (2,)            ``[width, height]`` pixels
``cam_int``           (T, 3, 3)       intrinsics ``K`` per frame
``cam_ext``           (T, 4, 4)       world to camera ``[[R, t], [0, 0, 0, 1]]`` (OpenCV)
``cam_to_world``      (T, 4, 4)       its inverse, the JSON's ``camera.to_world``
``pose``              (P, T, 47)      BLSM unconstrained pose x
``global_orient``     (P, T, 3)       BLSM orientation, world axis-angle (about the model's root)
``transl``            (P, T, 3)       BLSM translation, world metres
``bone``, ``shape``   (P, Kb), (P, Ks)  bone and shape coefficients (one body per track)
``keypoints_3d``      (P, T, K, 3)    world metres
``keypoints_3d_cam``  (P, T, K, 3)    camera metres, ``R X + t``
``keypoints_2d``      (P, T, K, 2)    pixels
``visible``           (P, T, K) bool  the keypoint is seen (see :mod:`synth.dataset.format`)
``in_frame``          (P, T, K) bool  the keypoint projects into the image
``velocity_3d``       (P, T, K, 3)    world m/s, central differences of the posed body
``contact``           (P, T, 9) bool  ground contact per region of ``contact_names``
``contact_velocity``  (P, T, 9) bool  the velocity rule's contact, same regions
``contact_names``     (9,) str        :data:`synth.dataset.format.CONTACT_REGIONS`
``in_view``           (P, T) bool     at least one pixel of the person is in the image
``box_full``          (P, T, 4)       ``[x0, y0, x1, y1]`` of the whole projected mesh, pixels (NaN
                                      where the person is wholly behind the camera)
``subject``           (P,) str        subject id (``subjects/<id>.npz`` of the dataset)
``keypoint_names``    (K,) str        the keypoints' names
====================  ==============  =================================================================

``coco`` writes ``OUT/person_keypoints.json`` (``file_name`` relative to ``OUT/images``):
``keypoints`` ``[x, y, v] * 17`` in COCO order (v = 2 visible, 1 in frame but hidden, 0 out of frame
with x = y = 0), ``num_keypoints`` (v > 0), ``bbox`` ``[x, y, w, h]`` of the visible mask's pixel
edges, ``area`` its pixel count, ``iscrowd`` 0 and ``segmentation`` the person's mask as
uncompressed column-major RLE ``{"counts": [...], "size": [h, w]}`` (pycocotools' layout).

Every shard's SHA-256 is checked against the manifest (the images are copied as they are) and every
label is read and checked before anything is written, so a bad sample leaves no output.
The images are copied through a staging folder and moved into ``OUT/images`` only when all are
there; the annotation file (``sequences.json`` for ``sequences``, after every sequence's ``.npz``,
each written atomically) is written last and atomically (:func:`blsm.io.atomic_write`): its
presence means a complete export. An existing one is an error unless ``overwrite``.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle

from blsm.io import atomic_write
from synth.dataset import format as sample_format
from synth.dataset.format import CONTACT_REGIONS
from synth.dataset.index import DatasetIndex

FORMATS = ("spin", "coco", "sequences")
SPIN_FILE = "blsm_synth.npz"
COCO_FILE = "person_keypoints.json"
SEQUENCES_FILE = "sequences.json"
_TARGETS = {"spin": SPIN_FILE, "coco": COCO_FILE, "sequences": SEQUENCES_FILE}

SPIN_KEYPOINTS: tuple[tuple[str, str | None], ...] = (
    ("r_ankle", "right_ankle"),
    ("r_knee", "right_knee"),
    ("r_hip", "right_hip"),
    ("l_hip", "left_hip"),
    ("l_knee", "left_knee"),
    ("l_ankle", "left_ankle"),
    ("r_wrist", "right_wrist"),
    ("r_elbow", "right_elbow"),
    ("r_shoulder", "right_shoulder"),
    ("l_shoulder", "left_shoulder"),
    ("l_elbow", "left_elbow"),
    ("l_wrist", "left_wrist"),
    ("neck_lsp", "neck"),  # BLSM's neck joint: the base of the neck, as LSP annotates it
    ("head_top_lsp", "head_top"),
    ("pelvis_mpii", "pelvis"),
    ("thorax_mpii", None),
    ("spine_h36m", None),
    ("jaw_h36m", None),
    ("head_h36m", None),
    ("nose", "nose"),
    ("l_eye", "left_eye"),
    ("r_eye", "right_eye"),
    ("l_ear", "left_ear"),
    ("r_ear", "right_ear"),
)
"""SPIN's 24 keypoints in its order and the dataset keypoint each is taken from (None: missing)."""

COCO_KEYPOINTS = (
    "nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip",
    "left_knee", "right_knee", "left_ankle", "right_ankle",
)  # fmt: skip
COCO_SKELETON = (
    (16, 14), (14, 12), (17, 15), (15, 13), (12, 13), (6, 12), (7, 13), (6, 7), (6, 8), (7, 9),
    (8, 10), (9, 11), (2, 3), (1, 2), (1, 3), (2, 4), (3, 5), (4, 6), (5, 7),
)  # fmt: skip


def rle_encode(mask: np.ndarray) -> dict[str, Any]:
    """(H, W) bool mask to pycocotools' uncompressed RLE: column-major runs, starting with zeros."""
    flat = np.asarray(mask, bool).reshape(-1, order="F")
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    bounds = np.concatenate([[0], change, [flat.size]])
    counts = np.diff(bounds).tolist()
    if flat.size and flat[0]:
        counts = [0, *counts]
    return {"counts": [int(c) for c in counts], "size": [int(mask.shape[0]), int(mask.shape[1])]}


def _camera_orient(orient: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """(N, 3) axis-angle ``global_orient`` and (N, 3, 3) ``R`` to camera-frame axis-angle."""
    rg = axis_angle_to_rotation_matrix(torch.as_tensor(orient, dtype=torch.float64))
    return rotation_matrix_to_axis_angle(torch.as_tensor(rot, dtype=torch.float64) @ rg).numpy()


def _spin_row(
    meta: dict[str, Any], q: dict[str, Any], names: list[str], scale_factor: float
) -> dict[str, Any]:
    kp2, kp3 = np.asarray(q["keypoints_2d"], np.float64), np.asarray(q["keypoints_3d_cam"], np.float64)
    seen, in_frame = sample_format.seen_keypoints(q), np.asarray(q["in_frame"], bool)
    part, s3, visible = np.zeros((24, 3)), np.zeros((24, 4)), np.zeros(24, bool)
    for j, (_, ours) in enumerate(SPIN_KEYPOINTS):
        if ours is not None and ours in names:
            k = names.index(ours)
            # SPIN's convention (its COCO preprocessing: COCO v > 0): 1 for every joint labelled in the
            # image, occluded or not; whether it is seen is kept apart, in ``visible``.
            part[j] = [*kp2[k], float(in_frame[k])]
            s3[j] = [*kp3[k], 1.0]
            visible[j] = seen[k]
    x0, y0, x1, y1 = sample_format.person_box(q)
    b = q["blsm"]
    return {
        "center": [(x0 + x1) / 2, (y0 + y1) / 2],
        "scale": scale_factor * max(x1 - x0, y1 - y0) / 200.0,
        "part": part,
        "visible": visible,
        "S": s3,
        "pose": b["pose"],
        "angles": b["angles"],
        "bone": b["bone"],
        "shape": b["shape"],
        "global_orient": b["global_orient"],
        "R": meta["camera"]["R"],
        "transl_cam": kp3[names.index("pelvis")],
        "K": meta["camera"]["K"],
    }


def _coco_ann(q: dict[str, Any], names: list[str], own: np.ndarray) -> dict[str, Any]:
    kp2 = np.asarray(q["keypoints_2d"], np.float64)
    vis, in_frame = np.asarray(q["visible"], bool), np.asarray(q["in_frame"], bool)
    flat: list[float] = []
    for n in COCO_KEYPOINTS:
        k = names.index(n)
        v = 2 if vis[k] and in_frame[k] else 1 if in_frame[k] else 0
        flat += [float(kp2[k, 0]), float(kp2[k, 1]), v] if v else [0.0, 0.0, 0]
    x0, y0, x1, y1 = sample_format.person_box(q)
    return {
        "category_id": 1,
        "keypoints": flat,
        "num_keypoints": sum(1 for v in flat[2::3] if v > 0),
        "bbox": [x0, y0, x1 - x0, y1 - y0],
        "area": float(own.sum()),
        "iscrowd": 0,
        "segmentation": rle_encode(own),
    }


def _copy_images(index: DatasetIndex, folder: Path) -> None:
    """Every sample's ``rgb.png`` to ``folder/<key>.png``: written into a staging folder beside it
    and moved in only when all are there; the staging folder is removed on any failure."""
    import shutil
    import tempfile

    folder.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=".images.", suffix=".tmp", dir=folder.parent))
    try:
        for i in range(len(index)):
            key = index.samples[i][1]
            (stage / f"{key}.png").write_bytes(index.read(i, ("rgb.png",))["rgb.png"])
        folder.mkdir(exist_ok=True)
        for f in sorted(stage.iterdir()):
            f.replace(folder / f.name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def export(
    path: str | Path,
    fmt: str,
    out: str | Path,
    overwrite: bool = False,
    min_pixels: int = 1,
    scale_factor: float = 1.2,
) -> Path:
    """Export the dataset at ``path`` as ``fmt`` (``"spin"``, ``"coco"`` or ``"sequences"``) into ``out``.

    Args:
        path: dataset folder (``manifest.json`` and shards).
        fmt: ``"spin"``, ``"coco"`` or ``"sequences"`` (a video dataset; see the module docstring).
        out: output folder; ``out/images/`` receives the images.
        overwrite: replace an existing export in ``out``.
        min_pixels: skip persons with fewer visible mask pixels (``spin`` and ``coco``).
        scale_factor: SPIN's box enlargement in ``scale``.

    Returns:
        The annotation file written (``sequences.json`` for ``sequences``).

    Raises:
        ValueError: one line, on an unknown format, a bad dataset (naming the file) or an existing
            export without ``overwrite``.
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; choose one of {list(FORMATS)}")
    index = DatasetIndex(path, verify=True)  # the images are copied as they are: check their bytes
    out = Path(out)
    target = out / _TARGETS[fmt]
    if target.exists() and not overwrite:
        raise ValueError(f"{target}: an export already exists; pass overwrite=True to replace it")
    if fmt == "sequences":
        return _export_sequences(index, out, target)
    # Pass 1 reads and checks every label before anything is written: bad labels leave no output.
    rows: list[dict[str, Any]] = []
    imgnames: list[str] = []
    coco: dict[str, Any] = {"images": [], "annotations": []}
    for i in range(len(index)):
        key, where = index.samples[i][1], index.where(i)
        raw = index.read(i, ("json",) + (("mask.png",) if fmt == "coco" else ()))
        meta = sample_format.decode_json(raw["json"], f"{where}.json")
        mask = sample_format.decode_png(raw["mask.png"], f"{where}.mask.png") if fmt == "coco" else None
        try:
            names = list(meta["keypoint_names"])
            if fmt == "coco":
                img = meta["image"]
                coco["images"].append(
                    {
                        "id": int(meta["index"]),
                        "file_name": f"{key}.png",
                        "width": img["width"],
                        "height": img["height"],
                    }
                )
            for p, q in enumerate(meta["people"]):
                if q["pixels"] < min_pixels:
                    continue
                if fmt == "spin":
                    rows.append(_spin_row(meta, q, names, scale_factor))
                    imgnames.append(f"images/{key}.png")
                else:
                    ann = _coco_ann(q, names, mask == p + 1)
                    ann.update(id=len(coco["annotations"]) + 1, image_id=int(meta["index"]))
                    coco["annotations"].append(ann)
        except (KeyError, IndexError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}.json: bad labels ({exc})") from None
    if fmt == "spin" and not rows:
        raise ValueError(
            f"{index.root}: no person has {min_pixels} or more visible pixels; nothing to export"
        )
    # Pass 2 copies the images through a staging folder (a failed copy leaves none of them), then
    # the annotation file is written last, atomically.
    _copy_images(index, out / "images")
    if fmt == "coco":
        coco["categories"] = [
            {"id": 1, "name": "person", "supercategory": "person", "keypoints": list(COCO_KEYPOINTS),
             "skeleton": [list(e) for e in COCO_SKELETON]}
        ]  # fmt: skip
        coco["info"] = {"description": f"BLSM synthetic dataset {index.root}", "pixel_center": 0.5}
        with atomic_write(target, "w") as f:
            json.dump(coco, f)
        return target
    arrays: dict[str, np.ndarray] = {"imgname": np.array(imgnames, dtype=str)}
    for name in ("center", "scale", "part", "S", "pose", "angles", "bone", "shape", "transl_cam", "K"):
        arrays[name] = np.array([r[name] for r in rows], dtype=np.float64)
    orient = np.array([r["global_orient"] for r in rows], np.float64)
    arrays["visible"] = np.array([r["visible"] for r in rows], bool).reshape(len(rows), 24)
    arrays["global_orient"] = _camera_orient(orient, np.array([r["R"] for r in rows], np.float64))
    arrays["has_smpl"] = np.zeros(len(rows), np.float64)
    arrays["has_blsm"] = np.ones(len(rows), np.float64)
    with atomic_write(target) as f:
        np.savez(f, **arrays)
    return target


def _sequence_frame(meta: dict[str, Any], key: str) -> dict[str, Any]:
    """One frame's labels as arrays: camera, and per person (P, ...) in track order."""
    cam, people = meta["camera"], meta["people"]
    if [q["track"] for q in people] != list(range(len(people))):
        raise ValueError("people must be listed in track order 0 .. P-1")
    ext = np.eye(4)
    ext[:3, :3], ext[:3, 3] = cam["R"], cam["t"]

    def each(name: str, dtype: Any = np.float64) -> np.ndarray:
        return np.array([q[name] for q in people], dtype)

    return {
        "imgname": f"images/{key}.png",
        "frame": int(meta["frame"]),
        "time": float(meta["time"]),
        "fps": float(meta["fps"]),
        "image_size": [int(meta["image"]["width"]), int(meta["image"]["height"])],
        "cam_int": np.asarray(cam["K"], np.float64).reshape(3, 3),
        "cam_ext": ext,
        "cam_to_world": np.asarray(cam["to_world"], np.float64).reshape(4, 4),
        "pose": np.array([q["blsm"]["pose"] for q in people], np.float64),
        "global_orient": np.array([q["blsm"]["global_orient"] for q in people], np.float64),
        "transl": np.array([q["blsm"]["transl"] for q in people], np.float64),
        "bone": np.array([q["blsm"]["bone"] for q in people], np.float64),
        "shape": np.array([q["blsm"]["shape"] for q in people], np.float64),
        "keypoints_3d": each("keypoints_3d"),
        "keypoints_3d_cam": each("keypoints_3d_cam"),
        "keypoints_2d": each("keypoints_2d"),
        "visible": each("visible", bool),
        "in_frame": each("in_frame", bool),
        "velocity_3d": each("velocity_3d"),
        "contact": np.array([[q["contact"][r] for r in CONTACT_REGIONS] for q in people], bool),
        "contact_velocity": np.array(
            [[q["contact_velocity"][r] for r in CONTACT_REGIONS] for q in people], bool
        ),
        "in_view": each("in_view", bool),
        "box_full": np.array([q["box_full"] if q["box_full"] is not None else [np.nan] * 4 for q in people], np.float64),
        "subject": [str(q["subject"]) for q in people],
        "keypoint_names": [str(n) for n in meta["keypoint_names"]],
    }


_PER_FRAME = ("frame", "time", "cam_int", "cam_ext", "cam_to_world")
_PER_PERSON = (
    "pose", "global_orient", "transl", "keypoints_3d", "keypoints_3d_cam", "keypoints_2d", "visible",
    "in_frame", "velocity_3d", "contact", "contact_velocity", "in_view", "box_full",
)  # fmt: skip
_CONSTANT = ("fps", "image_size", "subject", "keypoint_names", "bone", "shape")  # the same in every frame


def _sequence_arrays(frames: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """The ``.npz`` arrays of a sequence from its frames' :func:`_sequence_frame` rows (in order)."""
    first = frames[0]
    for f in frames[1:]:
        for name in _CONSTANT:
            if not np.array_equal(np.asarray(f[name]), np.asarray(first[name])):
                raise ValueError(f"{name} differs from frame 0's in frame {f['frame']}")
    out = {"imgname": np.array([f["imgname"] for f in frames], dtype=str)}
    out.update({k: np.array([f[k] for f in frames]) for k in _PER_FRAME})
    for k in _PER_PERSON:
        stacked = np.stack([f[k] for f in frames])  # (T, P, ...)
        out[k] = np.moveaxis(stacked, 0, 1)  # (P, T, ...)
    out.update(
        fps=np.array(first["fps"]),
        image_size=np.array(first["image_size"]),
        bone=first["bone"],
        shape=first["shape"],
        subject=np.array(first["subject"], dtype=str),
        keypoint_names=np.array(first["keypoint_names"], dtype=str),
        contact_names=np.array(CONTACT_REGIONS, dtype=str),
    )
    return out


def _sequences(index: DatasetIndex) -> Iterator[tuple[int, dict[str, np.ndarray]]]:
    """Each sequence's id and ``.npz`` arrays, in order, from the frames' labels (a ValueError
    naming the file on bad labels, a frame missing or repeated, or a dataset of single images)."""
    frames: dict[int, dict[str, Any]] = {}
    seq, length, where0 = -1, 0, ""

    def done() -> tuple[int, dict[str, np.ndarray]]:
        if sorted(frames) != list(range(length)):
            raise ValueError(f"{where0}: sequence {seq} has {len(frames)} of its {length} frames")
        try:
            return seq, _sequence_arrays([frames[f] for f in range(length)])
        except ValueError as exc:
            raise ValueError(f"{where0}: sequence {seq}: bad labels ({exc})") from None

    seen: set[int] = set()
    for i in range(len(index)):
        key, where = index.samples[i][1], index.where(i)
        meta = sample_format.decode_json(index.read(i, ("json",))["json"], f"{where}.json")
        if not isinstance(meta, dict) or "sequence" not in meta:
            raise ValueError(f"{where}.json: no 'sequence' label: not a video dataset (docs/video.md)")
        try:
            s, f = int(meta["sequence"]), int(meta["frame"])
            if s != seq:
                if frames:
                    yield done()
                if s in seen:
                    raise ValueError(f"frames of sequence {s} are not contiguous in the shards")
                seen.add(s)
                frames, seq, length, where0 = {}, s, int(meta["frames"]), where
            if f in frames:
                raise ValueError(f"frame {f} of sequence {s} appears twice")
            frames[f] = _sequence_frame(meta, key)
        except (KeyError, IndexError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}.json: bad labels ({exc})") from None
    if frames:
        yield done()


def _export_sequences(index: DatasetIndex, out: Path, target: Path) -> Path:
    """``format="sequences"``: check every label, then write the images, each sequence's ``.npz``
    and, last, ``sequences.json`` listing them (the module docstring)."""
    # Pass 1 checks every sequence without keeping it (a dataset's arrays may not fit in memory).
    count = sum(1 for _ in _sequences(index))
    if not count:
        raise ValueError(f"{index.root}: the dataset holds no samples; nothing to export")
    old: list[str] = []
    if target.exists():  # overwrite: the old export's files that the new one does not replace go
        try:
            old = list(json.loads(target.read_text())["sequences"])
        except (OSError, ValueError, KeyError, TypeError):
            old = []
    # Pass 2: the images, each sequence's .npz (atomically), then the list of them, last.
    _copy_images(index, out / "images")
    target.unlink(missing_ok=True)  # an overwritten export is incomplete until the new list is written
    names, fps, length = [], 0.0, 0
    for s, arrays in _sequences(index):
        names.append(f"{s:06d}.npz")
        fps, length = float(arrays["fps"]), len(arrays["frame"])
        with atomic_write(out / names[-1]) as f:
            np.savez(f, **arrays)
    for name in set(old) - set(names):
        if Path(name).name == name and name.endswith(".npz"):
            (out / name).unlink(missing_ok=True)
    doc = {"sequences": names, "frames": length, "fps": fps, "contact_names": list(CONTACT_REGIONS)}
    with atomic_write(target, "w") as f:
        json.dump(doc, f, indent=1)
    return target
