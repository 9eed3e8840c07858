"""Registration files: one scan brought into the template topology, written and read back.

A registration (``blsm-registration`` v1, :class:`Registration`, written by :func:`save_registration`)
holds the registered mesh ``vertices`` (V, 3) in metres, world frame (Y up), the stage-1 skeleton
(bone scales, angles, global orientation, translation), the T-pose displacements and a ``meta`` JSON
with the subject id, the pose id and the split (``"train"`` or ``"test"``).

Two readers, for two jobs:

- :func:`load_registrations`: whole registrations, strictly checked, for learning the model
  (:mod:`blsm.learn.training.train`).
- :func:`load_registration_set`: only the meshes and their labels of a folder of registration-like
  files (``vertices`` and ``meta``; ground truth when it can be found), as a
  :class:`RegistrationSet`, for the held-out evaluation (:mod:`blsm.learn.evaluation.evaluate`), the
  SMPL-reimpl baseline's training (:mod:`blsm.learn.evaluation.smpl_reimpl`) and the pipeline
  (:mod:`blsm.learn.pipeline`); :func:`spread_over_subjects` picks a subset of it that covers many
  subjects.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm.io import read_versioned_npz, write_versioned_npz

__all__ = [
    "Registration",
    "RegistrationSet",
    "correspondence_error",
    "load_registration",
    "load_registration_set",
    "load_registrations",
    "save_registration",
    "spread_over_subjects",
]

FORMAT = "blsm-registration"
FORMAT_VERSION = 1


# ------------------------------------------------------------------------------------------------
# One registration file


@dataclass
class Registration:
    """One registered scan in BLSM topology ("blsm-registration" v1).

    Attributes:
        vertices: (V, 3) the registered, posed mesh S^ (Eq. 5.14's result), metres, world frame.
        bone_scales: (J,) global bone scales b.
        angles: (47,) atom angles, radians.
        global_orient: (3,) axis-angle. transl: (3,) metres.
        displacement: (V, 3) V_D in the T-pose frame: ``S^ = LBS(V_T + V_D, T(b, theta))``.
        meta: scan id, subject, pose id, split, errors in mm, iterations, seconds.
    """

    vertices: np.ndarray
    bone_scales: np.ndarray
    angles: np.ndarray
    global_orient: np.ndarray
    transl: np.ndarray
    displacement: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)


_REG_ARRAYS: dict[str, tuple[str, ...]] = {
    "vertices": ("V", "3"),
    "bone_scales": ("J",),
    "angles": ("D",),
    "global_orient": ("3",),
    "transl": ("3",),
    "displacement": ("V", "3"),
}


def save_registration(reg: Registration, path: str | Path) -> Path:
    """Write a "blsm-registration" v1 ``.npz`` atomically (float32 arrays)."""
    path = Path(path)
    arrays = {k: np.asarray(getattr(reg, k), dtype=np.float32) for k in _REG_ARRAYS}
    _check_registration(arrays, str(path))
    entries = {"meta": np.array(json.dumps(reg.meta, sort_keys=True)), **arrays}
    return write_versioned_npz(path, FORMAT, FORMAT_VERSION, entries)


def load_registration(path: str | Path) -> Registration:
    """Read and validate a "blsm-registration" v1 file; errors are one line naming the file."""
    path = Path(path)
    raw = read_versioned_npz(path, FORMAT, FORMAT_VERSION, "registration")
    missing = [k for k in (*_REG_ARRAYS, "meta") if k not in raw]
    if missing:
        raise ValueError(f"{path}: missing arrays {missing}")
    try:
        meta = json.loads(str(raw["meta"]))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: meta is not JSON ({exc})") from None
    arrays = {k: raw[k].astype(np.float32) for k in _REG_ARRAYS}
    _check_registration(arrays, str(path))
    return Registration(**arrays, meta=meta)


def _check_registration(arrays: dict[str, np.ndarray], where: str) -> None:
    dims: dict[str, int] = {"3": 3}
    for k, shape in _REG_ARRAYS.items():
        a = arrays[k]
        if a.ndim != len(shape) or any(dims.setdefault(n, s) != s for n, s in zip(shape, a.shape)):
            raise ValueError(f"{where}: array {k!r} has shape {a.shape}, expected {shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"{where}: array {k!r} is not finite")


def load_registrations(paths: Sequence[str | Path]) -> list[Registration]:
    """Read registration files (:func:`load_registration`); folders are expanded to their ``*.npz``
    files in sorted order."""
    files: list[Path] = []
    for p in map(Path, paths):
        files.extend(sorted(p.glob("*.npz")) if p.is_dir() else [p])
    if not files:
        raise ValueError(f"no registration files in {', '.join(map(str, paths))}")
    return [load_registration(f) for f in files]


def correspondence_error(reg: Registration, gt_points: Any) -> tuple[float, float]:
    """Mean and max per-vertex distance in millimetres between ``reg.vertices`` and ground truth.

    Args:
        reg: a registration (or anything with ``vertices`` (V, 3) metres).
        gt_points: (V, 3) true positions of the template vertices on the scan, metres.

    Returns:
        (mean_mm, max_mm).
    """
    v = np.asarray(reg.vertices, dtype=np.float64)
    g = np.asarray(gt_points, dtype=np.float64)
    if v.shape != g.shape:
        raise ValueError(f"gt_points must be {v.shape}, got {g.shape}")
    d = np.linalg.norm(v - g, axis=1) * 1000.0
    return float(d.mean()), float(d.max())


# ------------------------------------------------------------------------------------------------
# A folder of registrations as one set of meshes


@dataclass
class RegistrationSet:
    """Registrations in the model topology with their labels.

    Attributes:
        vertices: (N, V, 3) registered meshes, metres, world frame.
        subjects: (N,) subject ids.
        pose_ids: (N,) pose / frame ids (as strings).
        splits: (N,) "train" or "test".
        names: (N,) file names.
        gt_points: per registration the (V, 3) ground-truth surface points or None.
    """

    vertices: torch.Tensor
    subjects: list[str]
    pose_ids: list[str]
    splits: list[str]
    names: list[str]
    gt_points: list[np.ndarray | None] = field(default_factory=list)

    def select(self, idx: list[int]) -> RegistrationSet:
        return RegistrationSet(
            self.vertices[idx],
            [self.subjects[i] for i in idx],
            [self.pose_ids[i] for i in idx],
            [self.splits[i] for i in idx],
            [self.names[i] for i in idx],
            [self.gt_points[i] for i in idx] if self.gt_points else [],
        )

    def split(self, name: str) -> RegistrationSet:
        return self.select([i for i, s in enumerate(self.splits) if s == name])

    def ground_truth(self) -> RegistrationSet:
        """The same set with the true bodies (``gt_points``) as the meshes to fit, no registration error.

        Fitting a model to the true bodies measures the model alone: the registrations' own error
        (mostly sliding along the surface) is no longer part of what the model must reproduce.
        """
        for name, g in zip(self.names, self.gt_points or [None] * len(self.names), strict=True):
            if g is None:
                raise ValueError(f"{name}: no ground-truth points (gt_points) to fit to")
        gt = torch.from_numpy(np.stack(self.gt_points).astype(np.float32))
        return RegistrationSet(
            gt, list(self.subjects), list(self.pose_ids), list(self.splits), list(self.names), []
        )


def _meta_get(meta: dict, *keys: str, default: str = "") -> str:
    for k in keys:
        if k in meta and meta[k] is not None:
            return str(meta[k])
    return default


def _find_gt(meta: dict, reg_dir: Path, scans_dir: Path | None) -> np.ndarray | None:
    candidates = []
    for key in ("scan_path", "scan"):
        if isinstance(meta.get(key), str):
            p = Path(meta[key])
            candidates += [p, reg_dir / p, reg_dir.parent / p]
            if scans_dir is not None:
                candidates += [scans_dir / p, scans_dir / "scans" / p.name]
    scan_id = _meta_get(meta, "scan_id", "scan id", "scan", "id")  # register.py writes "scan"
    if scans_dir is not None and scan_id:
        candidates += [scans_dir / "scans" / f"{scan_id}.npz", scans_dir / f"{scan_id}.npz"]
    for p in candidates:
        if p.suffix == ".npz" and p.is_file():
            with np.load(p, allow_pickle=False) as z:
                if "gt_points" in z.files:
                    return np.asarray(z["gt_points"], dtype=np.float32)
    return None


def load_registration_set(
    folder: str | Path, num_vertices: int, scans_dir: str | Path | None = None
) -> RegistrationSet:
    """Read every ``*.npz`` registration in ``folder`` (recursively), sorted by subject and pose.

    Args:
        folder: a folder of ``blsm-registration`` files (``vertices`` (V, 3), ``meta`` JSON with
            ``subject``, ``pose_id``/``pose``, ``split``; ``gt_points`` or a findable scan optional).
        num_vertices: V of the model; files with another vertex count are an error.
        scans_dir: population folder or scan folder where ground-truth scans can be looked up.

    Returns:
        :class:`RegistrationSet` (vertices float32).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: not a folder of registrations")
    files = sorted(p for p in folder.rglob("*.npz") if not p.name.startswith("."))
    if not files:
        raise ValueError(f"{folder}: no .npz registrations found")
    rows = []
    for path in files:
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: cannot read registration ({exc})") from exc
        if "vertices" not in arrays:
            raise ValueError(f"{path}: missing array 'vertices'")
        verts = np.asarray(arrays["vertices"], dtype=np.float32)
        if verts.shape != (num_vertices, 3) or not np.isfinite(verts).all():
            raise ValueError(f"{path}: vertices must be finite ({num_vertices}, 3), got {verts.shape}")
        meta_raw = arrays.get("meta", arrays.get("meta_json", np.array("{}")))
        try:
            meta = json.loads(str(meta_raw))
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: meta is not JSON ({exc})") from exc
        split = _meta_get(meta, "split", default="test")
        if split not in ("train", "test"):
            raise ValueError(f"{path}: split must be 'train' or 'test', got {split!r}")
        gt = arrays.get("gt_points")
        if gt is None:
            gt = _find_gt(meta, folder, None if scans_dir is None else Path(scans_dir))
        rows.append(
            (
                _meta_get(meta, "subject", "subject_id", default=path.stem),
                _meta_get(meta, "pose_id", "pose id", "pose", "frame", default=path.stem),
                split,
                path.name,
                verts,
                None if gt is None or np.shape(gt) != (num_vertices, 3) else np.asarray(gt, np.float32),
            )
        )
    rows.sort(key=lambda r: (r[0], _natural(r[1]), r[3]))
    return RegistrationSet(
        torch.from_numpy(np.stack([r[4] for r in rows])),
        [r[0] for r in rows],
        [r[1] for r in rows],
        [r[2] for r in rows],
        [r[3] for r in rows],
        [r[5] for r in rows],
    )


def spread_over_subjects(subjects: list[str], n: int, sequences: int = 0) -> list[int]:
    """Indices of up to ``n`` registrations that cover as many subjects as they can.

    First every registration of the first ``sequences`` subjects (sorted) that have more than one,
    so that shape can be fitted on one frame and pose on the others (Fig. 5.7 right); then the rest
    of the budget round-robin over the other subjects: every subject's first registration, then
    every subject's second, and so on. The first ``n`` in file order may hold only a few subjects.
    """
    by_subject: dict[str, list[int]] = {}
    for i, s in enumerate(subjects):
        by_subject.setdefault(s, []).append(i)
    order = sorted(by_subject, key=_natural)
    out: list[int] = []
    whole = [s for s in order if len(by_subject[s]) > 1][:max(sequences, 0)]
    for s in whole:
        out += by_subject[s][:max(n - len(out), 0)]
    rest = [s for s in order if s not in whole]
    for r in range(max((len(by_subject[s]) for s in rest), default=0)):
        for s in rest:
            if r < len(by_subject[s]) and len(out) < n:
                out.append(by_subject[s][r])
    return sorted(out)


def _natural(s: str) -> tuple:
    return (0, int(s), "") if s.isdigit() else (1, 0, s)
