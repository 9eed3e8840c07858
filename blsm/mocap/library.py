"""The motion library: one ``.npz`` file per retargeted clip.

Format "blsm-motion", version 1 (``numpy.savez``, no pickles):

=====================  ===========  ======================================================
key                    shape/dtype  meaning
=====================  ===========  ======================================================
``pose``               (T, 47) f4   unconstrained atom values x (Eq. 6 gives the angles)
``global_orient``      (T, 3) f4    axis-angle root rotation (world frame, Y up)
``transl``             (T, 3) f4    root translation in metres for the mean body (floor y=0)
``dir_err_mean_deg``   (T,) f4      mean segment-direction error vs. the source, degrees
``dir_err_max_deg``    (T,) f4      max segment-direction error, degrees
``mpjpe_mm``           (T,) f4      MPJPE vs. the source chain at BLSM lengths, millimetres
``segment_err_deg``    (T, S) f4    per-segment direction error (``meta.segments``)
``meta``               str (JSON)   format, version, fps, source file and its SHA-256,
                                    mapping table, units, leg-length ratio, DoF names
=====================  ===========  ======================================================

Read with :func:`load_clip`; a clip feeds the model directly::

    clip = load_clip("motions/005_02.npz")
    out = model(pose=torch.as_tensor(clip.pose), global_orient=..., transl=...)
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from blsm.io import atomic_write, read_npz, sha256_file

sha256 = sha256_file  # the clip's ``source_sha256``

FORMAT = "blsm-motion"
VERSION = 1
_ARRAYS = {
    "pose": 2,
    "global_orient": 2,
    "transl": 2,
    "dir_err_mean_deg": 1,
    "dir_err_max_deg": 1,
    "mpjpe_mm": 1,
    "segment_err_deg": 2,
}


@dataclass
class MotionClip:
    """A retargeted clip; see the module docstring for the arrays."""

    name: str
    fps: float
    pose: np.ndarray
    global_orient: np.ndarray
    transl: np.ndarray
    dir_err_mean_deg: np.ndarray
    dir_err_max_deg: np.ndarray
    mpjpe_mm: np.ndarray
    segment_err_deg: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    @property
    def num_frames(self) -> int:
        return int(self.pose.shape[0])


def validate(clip: MotionClip, where: str) -> None:
    """Check shapes, dtypes and finiteness; raise ``ValueError(f"{where}: ...")``."""
    t = clip.pose.shape[0] if clip.pose.ndim == 2 else -1
    n_dof = len(clip.meta.get("dof_names", []))
    if clip.pose.ndim != 2 or clip.pose.shape[1] != n_dof or n_dof == 0:
        raise ValueError(f"{where}: pose must be (T, {n_dof or 47}), got {clip.pose.shape}")
    if t < 1:
        raise ValueError(f"{where}: the clip has no frames")
    expect = {
        "global_orient": (t, 3),
        "transl": (t, 3),
        "dir_err_mean_deg": (t,),
        "dir_err_max_deg": (t,),
        "mpjpe_mm": (t,),
        "segment_err_deg": (t, len(clip.meta.get("segments", []))),
    }
    for key, shape in expect.items():
        arr = getattr(clip, key)
        if arr.shape != shape:
            raise ValueError(f"{where}: {key} must have shape {shape}, got {arr.shape}")
    for key in _ARRAYS:
        if not np.isfinite(getattr(clip, key)).all():
            raise ValueError(f"{where}: {key} has non-finite values")
    if not (np.isfinite(clip.fps) and clip.fps > 0):
        raise ValueError(f"{where}: fps must be positive, got {clip.fps}")


def save_clip(clip: MotionClip, path: str | Path) -> Path:
    """Write a clip atomically (temporary file in the same folder, then ``os.replace``)."""
    path = Path(path)
    meta = dict(clip.meta, format=FORMAT, version=VERSION, name=clip.name, fps=float(clip.fps))
    validate(MotionClip(**{**clip.__dict__, "meta": meta}), str(path))
    with atomic_write(path) as f:
        np.savez(
            f,
            meta=np.array(json.dumps(meta)),
            **{k: np.asarray(getattr(clip, k), dtype=np.float32) for k in _ARRAYS},
        )
    return path


def load_clip(path: str | Path) -> MotionClip:
    """Read and validate a clip file; errors are one line naming the file."""
    path = Path(path)
    data = read_npz(path, "motion")
    if "meta" not in data:
        raise ValueError(f"{path}: not a motion file (no 'meta')")
    try:
        meta = json.loads(str(data["meta"]))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: meta is not JSON ({exc.msg})") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: meta must hold a JSON object")
    if meta.get("format") != FORMAT:
        raise ValueError(f"{path}: format is {meta.get('format')!r}, expected {FORMAT!r}")
    if meta.get("version") != VERSION:
        raise ValueError(f"{path}: format version {meta.get('version')} is not supported ({VERSION})")
    missing = [k for k in _ARRAYS if k not in data]
    if missing:
        raise ValueError(f"{path}: missing array {missing[0]!r}")
    clip = MotionClip(
        name=str(meta.get("name", path.stem)),
        fps=float(meta.get("fps", 0)),
        meta=meta,
        path=path,
        **{k: data[k] for k in _ARRAYS},
    )
    validate(clip, str(path))
    return clip


def list_clips(folder: str | Path) -> list[Path]:
    """The clip files of a library folder, sorted; an error if there are none."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: not a folder")
    files = sorted(p for p in folder.glob("*.npz") if not p.name.startswith("."))
    if not files:
        raise ValueError(f"{folder}: no motion files (*.npz)")
    return files
