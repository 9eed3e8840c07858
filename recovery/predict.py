"""``recovery predict CHECKPOINT PATH --out DIR``: the body of every person in a photograph, a folder of
photographs or a video.

PATH is an image, a folder (its image files, :data:`IMAGE_SUFFIXES`, not its sub-folders, by name) or a
video (:data:`VIDEO_SUFFIXES`; frames decoded with PyAV, ``--every N`` keeps every N-th frame and
``--max-frames M`` stops after M kept frames). In each image the person detector finds the people
(``--detect-passes``, :func:`recovery.detect.build_detector`): by default ``multi``
(:class:`recovery.detect.MultiPassDetector`: MoveNet MultiPose on the whole image and on overlapping
tiles, merged, each person scored again by MoveNet SinglePose, people scoring at least 0.2);
``single`` is one MultiPose pass on the image at 256 px (:class:`recovery.detect.PersonDetector`, up
to 6 people scoring at least 0.25). Each person is predicted from the square crop about its box's
centre of side 1.2 times the box's longer side (SPIN's rule). An image where nobody is found is listed
with no people and a one-line note.

An arbitrary photo has unknown intrinsics: the camera is taken as a pinhole with focal length
``--focal`` pixels (default: the image's longer side, about a 53-degree field of view) and the principal
point at the image centre; ``K_crop = A K`` with ``A`` the crop's affine map (pixel centres at integer +
0.5). The network predicts each body in that camera's frame (OpenCV: x right, y down, z forward; metres).

Writes, into DIR:

- ``people.json``: the run (checkpoint, detector settings, ``keypoint_names``) and per image (``image``:
  its file name, or ``frame``: the video frame's index from 0 with its ``time`` in seconds) its size,
  ``K``, the overlay's and meshes' file names and its ``people``, best score first, each with ``box``
  ``[x0, y0, x1, y1]`` (pixels), the detector's ``score`` and ``detector_keypoints`` (17 COCO ``(x, y,
  score)``), for HMR-BLSM the BLSM parameters (``pose`` x of Eq. 6, ``angles`` radians, ``bone``,
  ``shape``, ``global_orient`` axis-angle in the camera frame, the weak-perspective ``cam``), for either
  network ``transl`` (the pelvis in the camera frame), ``keypoints_3d_cam`` (metres) and
  ``keypoints_2d`` (those keypoints projected into the image, pixels), the ``crop`` and ``K_crop``;
- ``<name>_person<i>.obj`` per person: the mesh in the camera frame, metres;
- ``<name>_overlay.png`` per image: the image with the detected boxes | every person's mesh over it,
  depth-ordered (a nearer person hides a farther one), each person in the colour of its box.

``<name>`` is the image's file stem (the whole file name with ``.`` as ``_`` where two stems are equal)
or ``frame_<index>``. Everything is written to a hidden folder beside DIR and moved into DIR at the end,
so an error leaves DIR as it was; files of DIR with the same names as this run's outputs are replaced,
others are left alone.

``--box X0 Y0 X1 Y1`` (a single image) predicts that one person and writes what it always wrote:
``params.json`` (the fields above plus ``image``, ``checkpoint``, ``task``, ``K``), ``mesh.obj`` and
``overlay.png`` (the image | the mesh | its parts); ``--whole`` does the same with the whole image
padded to a square as the crop (what ``predict`` did without ``--box`` before the detector).

Video frames are read with PyAV (``av``): Python bindings of FFmpeg whose wheels bundle the FFmpeg
libraries (no system FFmpeg, every common container and codec), maintained by the PyAV project with
releases each few months; it hands out decoded frames as NumPy arrays with their time stamps. OpenCV's
reader would pull a second copy of FFmpeg and a large library for one function; imageio's FFmpeg plugin
runs a downloaded ffmpeg binary, which this project's machines cannot fetch.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm.io import atomic_write
from recovery.predictor import Prediction, Predictor, load_predictor
from recovery.utils.viz import draw_boxes, face_parts, overlay, parts_overlay, people_overlay
from synth.dataset.crops import crop_affine, map_points, warp_to_crop

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".gif", ".tif", ".tiff", ".webp", ".ppm", ".pgm")
"""Files of a folder that ``predict`` reads (case-insensitive)."""
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".flv", ".ts")
"""A PATH with one of these suffixes is read as a video."""
BOX_CONTEXT = 1.2
"""Crop side over the box's longer side (SPIN)."""
CONVENTIONS = "OpenCV camera (x right, y down, z forward), metres, radians; pixel centres at integer + 0.5"


def read_image(path: str | Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an image file; a ValueError names the file when it cannot be read."""
    from PIL import Image, UnidentifiedImageError
    from PIL.Image import DecompressionBombError

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such image")
    try:
        with Image.open(path) as im:
            return np.array(im.convert("RGB"))  # writable: torch.from_numpy warns on a read-only array
    except (UnidentifiedImageError, OSError, DecompressionBombError) as exc:  # bomb: > 179 Mpixels claimed
        raise ValueError(f"{path}: not a readable image ({exc})") from None


def camera(width: int, height: int, focal: float | None = None) -> np.ndarray:
    """(3, 3) the assumed pinhole: focal ``focal`` (default: the longer side), principal point at the
    image centre."""
    if focal is not None and focal <= 0:
        raise ValueError(f"--focal must be positive, got {focal}")
    f = float(focal or max(width, height))
    return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def box_crop(box: tuple[float, ...] | np.ndarray) -> tuple[tuple[float, float], float]:
    """A box ``x0, y0, x1, y1`` -> the crop's centre and side (:data:`BOX_CONTEXT` x its longer side)."""
    x0, y0, x1, y1 = (float(v) for v in box)
    return ((x0 + x1) / 2, (y0 + y1) / 2), max(x1 - x0, y1 - y0) * BOX_CONTEXT


def predict_crops(pr: Predictor, image: np.ndarray, crops: list[tuple[tuple[float, float], float]],
                  k: np.ndarray, guides: list[np.ndarray] | None = None) -> tuple[Prediction, torch.Tensor]:
    """Every crop (centre, side) of ``image`` through the network in one batch: the prediction and the
    (B, 3, 3) ``K_crop``. ``guides``: per crop, the detector's (17, 3) COCO keypoints of its person in
    image pixels (:meth:`recovery.predictor.Predictor.__call__`), or None."""
    src = torch.from_numpy(image).permute(2, 0, 1).float() / 255.0
    imgs, ks, gs = [], [], []
    for j, (centre, side) in enumerate(crops):
        a = crop_affine(centre, side, pr.crop)
        imgs.append(warp_to_crop(src, a, pr.crop))
        ks.append(torch.tensor(a @ k, dtype=torch.float32))
        if guides is not None:
            g = np.asarray(guides[j], np.float64).copy()
            g[:, :2] = map_points(g[:, :2], a)
            gs.append(torch.tensor(g, dtype=torch.float32))
    k_crop = torch.stack(ks)
    return pr(torch.stack(imgs), k_crop, torch.stack(gs) if gs else None), k_crop


def person_fields(pr: Predictor, res: Prediction, i: int, k: np.ndarray) -> dict[str, Any]:
    """Person ``i`` of a prediction as JSON fields: BLSM parameters (HMR-BLSM), ``transl``,
    ``keypoints_3d_cam`` and ``keypoints_2d`` (projected with the image's ``k``, pixels)."""
    from kornia.geometry.conversions import rotation_matrix_to_axis_angle

    from blsm.joint_limits import angles_from_unconstrained

    out: dict[str, Any] = {}
    if res.params is not None:
        p = res.params
        angles = angles_from_unconstrained(p.pose[i:i + 1], pr.body.dof_limits)[0]
        out.update(pose=p.pose[i].tolist(), angles=angles.tolist(), bone=p.bone[i].tolist(),
                   shape=p.shape[i].tolist(),
                   global_orient=rotation_matrix_to_axis_angle(p.orient[i:i + 1])[0].tolist(),
                   cam=p.cam[i].tolist())
    kp = (res.keypoints_3d[i] + res.transl[i]).double().numpy()  # (K, 3) camera frame
    uv = kp @ k.T
    out.update(transl=res.transl[i].tolist(), keypoints_3d_cam=kp.tolist(),
               keypoints_2d=(uv[:, :2] / uv[:, 2:3]).tolist())
    return out


def write_obj(path: Path, verts: np.ndarray, faces: np.ndarray, comment: str) -> None:
    with atomic_write(path, "w") as fh:
        fh.write(f"# recovery predict: {comment}; camera frame (OpenCV), metres\n")
        fh.write("".join(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in verts))
        fh.write("".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))


def write_png(path: Path, image: np.ndarray) -> None:
    from PIL import Image

    tmp = path.with_name(f".{path.name}.tmp.png")
    Image.fromarray(image).save(tmp)
    tmp.replace(path)


# -- one person: --box or --whole -----------------------------------------------------------------
def predict(checkpoint: str | Path, image_path: str | Path, out: str | Path,
            box: tuple[float, ...] | None = None, focal: float | None = None,
            flip: bool = False) -> dict[str, Any]:
    """Predict one person: the crop about ``box`` or, without it, the whole image padded to a square.
    Writes ``params.json``, ``mesh.obj`` and ``overlay.png`` into ``out`` and returns the parameters.
    ``flip``: HMR-BLSM with flip test-time augmentation (:func:`recovery.models.hmr.flip_average`)."""
    image = read_image(image_path)
    h, w = image.shape[:2]
    if box is not None:
        x0, y0, x1, y1 = box
        if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
            raise ValueError(f"--box {list(box)} is not inside the {w} x {h} image {image_path}")
        centre, side = box_crop(box)
    else:
        centre, side = (w / 2, h / 2), float(max(w, h))
    k = camera(w, h, focal)
    pr = load_predictor(checkpoint).use_flip(flip)
    res, k_crop = predict_crops(pr, image, [(centre, side)], k)
    params: dict[str, Any] = {
        "image": str(image_path), "checkpoint": str(pr.path), "task": pr.task,
        "box": list(box) if box else None,
        "crop": {"center": list(centre), "side": side, "size": pr.crop},
        "K": k.tolist(), "K_crop": k_crop[0].tolist(),
    }
    fields = person_fields(pr, res, 0, k)
    blsm_keys = ("pose", "angles", "bone", "shape", "global_orient", "cam")
    params.update({key: fields[key] for key in blsm_keys if key in fields})
    params.update({"transl": fields["transl"], "keypoint_names": list(pr.body.keypoint_names),
                   "keypoints_3d_cam": fields["keypoints_3d_cam"], "conventions": CONVENTIONS})
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    faces = pr.body.faces.numpy()
    verts = (res.vertices[0] + res.transl[0]).numpy()
    with atomic_write(out / "params.json", "w") as fh:
        fh.write(json.dumps(params, indent=1))
    write_obj(out / "mesh.obj", verts, faces, str(image_path))
    flabels = face_parts(faces, pr.body.vertex_parts.numpy())
    panel = np.concatenate([image, overlay(image, verts, faces, k),
                            parts_overlay(image, verts, faces, k, flabels)], axis=1)
    write_png(out / "overlay.png", panel)
    return params


# -- every person of images, folders and videos ---------------------------------------------------
@dataclass
class Source:
    """What PATH is: ``kind`` ``image`` / ``folder`` / ``video``, and its image files (image, folder)."""

    path: Path
    kind: str
    files: list[Path]


def open_source(path: str | Path) -> Source:
    """Classify PATH and check it can be read as far as is cheap (a folder holds images, a video opens
    and has a video stream).

    Raises:
        ValueError: ``PATH: problem`` (missing, empty folder, a folder without images, not a video).
    """
    path = Path(path)
    if path.is_dir():
        entries = [p for p in sorted(path.iterdir()) if not p.name.startswith(".")]
        if not entries:
            raise ValueError(f"{path}: empty folder")
        files = [p for p in entries if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
        if not files:
            raise ValueError(f"{path}: no images ({', '.join(IMAGE_SUFFIXES)}) in the folder")
        return Source(path, "folder", files)
    if not path.is_file():
        raise ValueError(f"{path}: no such image, folder or video")
    if path.suffix.lower() in VIDEO_SUFFIXES:
        with _open_video(path) as container:
            if not container.streams.video:
                raise ValueError(f"{path}: not a readable video (no video stream)")
        return Source(path, "video", [])
    return Source(path, "image", [path])


def _open_video(path: Path):
    import av

    try:
        return av.open(str(path))
    except (av.FFmpegError, OSError) as exc:
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ValueError(f"{path}: not a readable video ({why})") from None


def read_video(path: str | Path, every: int = 1,
               max_frames: int = 0) -> Iterator[tuple[int, float | None, np.ndarray]]:
    """The frames of a video's first video stream: ``(index from 0, time in seconds, (H, W, 3) uint8 RGB)``
    for every ``every``-th frame, at most ``max_frames`` of them (0: all).

    Raises:
        ValueError: the file cannot be opened or a frame cannot be decoded, or it has no frame.
    """
    import av

    path = Path(path)
    kept, index = 0, -1
    with _open_video(path) as container:
        if not container.streams.video:
            raise ValueError(f"{path}: not a readable video (no video stream)")
        try:
            for index, frame in enumerate(container.decode(container.streams.video[0])):
                if index % every:
                    continue
                time = float(frame.time) if frame.time is not None else None
                yield index, time, frame.to_ndarray(format="rgb24")
                kept += 1
                if max_frames and kept >= max_frames:
                    break
        except av.FFmpegError as exc:
            raise ValueError(f"{path}: frame {index + 1} cannot be decoded ({exc})") from None
    if kept == 0:
        raise ValueError(f"{path}: not a readable video (no frames)")


def _names(files: list[Path]) -> list[str]:
    stems = [p.stem for p in files]
    return stems if len(set(stems)) == len(stems) else [p.name.replace(".", "_") for p in files]


def _frames(src: Source, every: int, max_frames: int) -> Iterator[tuple[dict[str, Any], str, np.ndarray]]:
    """(the JSON key of the image, its output name, the image) for each image or kept frame."""
    if src.kind == "video":
        for index, time, image in read_video(src.path, every, max_frames):
            yield {"frame": index, "time": time}, f"frame_{index:06d}", image
        return
    for f, name in zip(src.files, _names(src.files), strict=True):
        yield {"image": f.name}, name, read_image(f)


class _Staging:
    """A hidden folder beside ``out`` that receives every output; :meth:`commit` moves its files into
    ``out`` (renaming it to ``out`` when ``out`` does not exist); on an error it is removed."""

    def __init__(self, out: Path) -> None:
        self.out = out
        if out.exists() and not out.is_dir():
            raise ValueError(f"{out}: exists and is not a folder")
        out.parent.mkdir(parents=True, exist_ok=True)
        self.dir = Path(tempfile.mkdtemp(prefix=f".{out.name}.predict-", dir=out.parent))

    def __enter__(self) -> _Staging:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self.dir.exists():
            shutil.rmtree(self.dir)

    def commit(self) -> None:
        if not self.out.exists():
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(self.dir, 0o777 & ~umask)  # mkdtemp's folder is private; DIR is an ordinary folder
            os.replace(self.dir, self.out)
            return
        for f in sorted(self.dir.iterdir(), key=lambda p: p.name == "people.json"):  # people.json last
            os.replace(f, self.out / f.name)


def predict_people(checkpoint: str | Path, path: str | Path, out: str | Path, focal: float | None = None,
                   flip: bool = False, min_score: float | None = None, detect_size: int | None = None,
                   every: int = 1, max_frames: int = 0, log: Any = print,
                   detect_passes: str = "multi") -> dict[str, Any]:
    """Every person of an image, folder or video (module docstring); returns what ``people.json`` holds.

    Args:
        checkpoint: a checkpoint file or ``default``.
        path: an image, a folder of images or a video.
        out: the output folder.
        focal: focal length in pixels (default: each image's longer side).
        flip: HMR-BLSM flip test-time augmentation.
        min_score: the detector's person score threshold (default: the detector's,
            :data:`recovery.detect.MULTI_MIN_SCORE` for several passes, :data:`recovery.detect.MIN_SCORE`
            for one).
        detect_size: each detector pass's input, longer side, pixels (default :data:`recovery.detect.SIZE`).
        every, max_frames: videos: keep every ``every``-th frame, at most ``max_frames`` (0: all).
        log: one line per image without people.
        detect_passes: ``multi``, ``tiles`` or ``single`` (:data:`recovery.detect.DETECT_PASSES`).

    Raises:
        ValueError: one line ``PATH: problem`` (nothing is written then).
    """
    from recovery.detect import DETECT_PASSES, SIZE, MultiPassDetector, build_detector
    from recovery.models.backbones.movenet import COCO_KEYPOINTS

    if every < 1 or max_frames < 0:
        raise ValueError(f"--every must be >= 1 and --max-frames >= 0, got {every} and {max_frames}")
    if focal is not None and focal <= 0:
        raise ValueError(f"--focal must be positive, got {focal}")
    if detect_passes not in DETECT_PASSES:
        raise ValueError(f"--detect-passes must be one of {', '.join(DETECT_PASSES)}, got {detect_passes!r}")
    src = open_source(path)
    pr = load_predictor(checkpoint).use_flip(flip)
    detector = build_detector(detect_passes, detect_size or SIZE, min_score)
    settings = {"name": "movenet_multipose", "passes": detect_passes, "size": detector.size,
                "min_score": detector.min_score}
    if isinstance(detector, MultiPassDetector):
        settings.update(overlap=detector.overlap, look="movenet_lightning" if detector.look else None)
    faces = pr.body.faces.numpy()
    out = Path(out)
    doc: dict[str, Any] = {
        "input": str(path), "kind": src.kind, "checkpoint": str(pr.path), "task": pr.task,
        "detector": settings,
        "crop": {"context": BOX_CONTEXT, "size": pr.crop},
        "keypoint_names": list(pr.body.keypoint_names), "detector_keypoint_names": list(COCO_KEYPOINTS),
        "conventions": CONVENTIONS, "images": [],
    }
    with _Staging(out) as stage:
        for key, name, image in _frames(src, every, max_frames):
            h, w = image.shape[:2]
            k = camera(w, h, focal)
            found = detector(image)
            entry: dict[str, Any] = {**key, "width": w, "height": h, "K": k.tolist(),
                                     "overlay": f"{name}_overlay.png", "people": []}
            meshes = []
            for d in found:  # people.json's box is the one cropped: --box with it predicts the same person
                d.box = np.round(d.box, 2)
            if found:
                crops = [box_crop(d.box) for d in found]
                res, k_crop = predict_crops(pr, image, crops, k, [d.keypoints for d in found])
                for i, (d, (centre, side)) in enumerate(zip(found, crops, strict=True)):
                    verts = (res.vertices[i] + res.transl[i]).numpy()
                    meshes.append(verts)
                    mesh = f"{name}_person{i}.obj"
                    write_obj(stage.dir / mesh, verts, faces, f"{path} {name} person {i}")
                    entry["people"].append({
                        "box": d.box.tolist(), "score": round(d.score, 4),
                        "detector_keypoints": np.round(d.keypoints, 2).tolist(),
                        **person_fields(pr, res, i, k),
                        "crop": {"center": list(centre), "side": side}, "K_crop": k_crop[i].tolist(),
                        "mesh": mesh,
                    })
            else:
                entry["note"] = "no person found"
                log(f"{path if src.kind == 'image' else key.get('image', name)}: no person found")
            panel = np.concatenate([draw_boxes(image, [d.box for d in found]),
                                    people_overlay(image, meshes, faces, k)], 1)
            write_png(stage.dir / entry["overlay"], panel)
            doc["images"].append(entry)
        with atomic_write(stage.dir / "people.json", "w") as fh:
            fh.write(json.dumps(doc, indent=1))
        stage.commit()
    return doc
