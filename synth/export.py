"""Export a generated dataset for SPIN/HMR-style loaders (``.npz``) or as COCO keypoints (JSON).

    synth export DATASET --format spin --out OUT    # or: export("data/val", "coco", "exports/val")

Both formats copy every sample's ``rgb.png`` unchanged to ``OUT/images/<key>.png`` and hold one
entry per person instance with at least ``min_pixels`` visible mask pixels. Pixel coordinates are
written as they are in the dataset: continuous OpenCV coordinates with pixel centres at integer
+ 0.5 (pixel ``(u, v)`` covers ``[u, u + 1) x [v, v + 1)``); COCO's own convention is ambiguous, so
subtract 0.5 where a tool puts pixel centres at integers.

``spin`` writes ``OUT/blsm_synth.npz`` (N persons; load with ``allow_pickle=False``):

================  ==============  ===================================================================
``imgname``       (N,) str        ``images/<key>.png``, relative to ``OUT``
``center``        (N, 2)          centre of the visible ``box`` (``box_full`` when none), pixels
``scale``         (N,)            ``scale_factor * max(w, h) / 200``: SPIN's preprocessing (1.2 box)
``part``          (N, 24, 3)      SPIN's 24 keypoints (:data:`SPIN_KEYPOINTS`): x, y, visibility;
                                  keypoints we do not have are 0 with visibility 0
``S``             (N, 24, 4)      the same keypoints in camera metres (not centred) and confidence
``pose``          (N, 47)         BLSM unconstrained pose x; ``angles`` (N, 47) radians
``bone``          (N, Kb)         bone coefficients; ``shape`` (N, Ks) shape coefficients
``global_orient`` (N, 3)          axis-angle in the camera frame, ``R R_global``
``transl_cam``    (N, 3)          pelvis in camera metres
``K``             (N, 3, 3)       camera intrinsics of the image
``has_smpl``      (N,)            0 (the bodies are BLSM, not SMPL); ``has_blsm`` (N,) 1
================  ==============  ===================================================================

``coco`` writes ``OUT/person_keypoints.json`` (``file_name`` relative to ``OUT/images``):
``keypoints`` ``[x, y, v] * 17`` in COCO order (v = 2 visible, 1 in frame but hidden, 0 out of frame
with x = y = 0), ``num_keypoints`` (v > 0), ``bbox`` ``[x, y, w, h]`` of the visible mask's pixel
edges, ``area`` its pixel count, ``iscrowd`` 0 and ``segmentation`` the person's mask as
uncompressed column-major RLE ``{"counts": [...], "size": [h, w]}`` (pycocotools' layout).

Every shard's SHA-256 is checked against the manifest (the images are copied as they are) and every
label is read and checked before anything is written, so a bad sample leaves no output.
The images are copied through a staging folder and moved into ``OUT/images`` only when all are
there; the annotation file is written last and atomically (:func:`blsm.io.atomic_write`): its
presence means a complete export. An existing one is an error unless ``overwrite``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle

from blsm.io import atomic_write
from synth import format as sample_format
from synth.data import DatasetIndex

FORMATS = ("spin", "coco")
SPIN_FILE = "blsm_synth.npz"
COCO_FILE = "person_keypoints.json"

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
    vis = sample_format.seen_keypoints(q)
    part, s3 = np.zeros((24, 3)), np.zeros((24, 4))
    for j, (_, ours) in enumerate(SPIN_KEYPOINTS):
        if ours is not None and ours in names:
            k = names.index(ours)
            part[j] = [*kp2[k], float(vis[k])]
            s3[j] = [*kp3[k], 1.0]
    x0, y0, x1, y1 = sample_format.person_box(q)
    b = q["blsm"]
    return {
        "center": [(x0 + x1) / 2, (y0 + y1) / 2],
        "scale": scale_factor * max(x1 - x0, y1 - y0) / 200.0,
        "part": part,
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
    """Export the dataset at ``path`` as ``fmt`` (``"spin"`` or ``"coco"``) into folder ``out``.

    Args:
        path: dataset folder (``manifest.json`` and shards).
        fmt: ``"spin"`` or ``"coco"`` (see the module docstring).
        out: output folder; ``out/images/`` receives the images.
        overwrite: replace an existing export in ``out``.
        min_pixels: skip persons with fewer visible mask pixels.
        scale_factor: SPIN's box enlargement in ``scale``.

    Returns:
        The annotation file written.

    Raises:
        ValueError: one line, on an unknown format, a bad dataset (naming the file) or an existing
            export without ``overwrite``.
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; choose one of {list(FORMATS)}")
    index = DatasetIndex(path, verify=True)  # the images are copied as they are: check their bytes
    out = Path(out)
    target = out / (SPIN_FILE if fmt == "spin" else COCO_FILE)
    if target.exists() and not overwrite:
        raise ValueError(f"{target}: an export already exists; pass overwrite=True to replace it")
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
    arrays["global_orient"] = _camera_orient(orient, np.array([r["R"] for r in rows], np.float64))
    arrays["has_smpl"] = np.zeros(len(rows), np.float64)
    arrays["has_blsm"] = np.ones(len(rows), np.float64)
    with atomic_write(target) as f:
        np.savez(f, **arrays)
    return target
