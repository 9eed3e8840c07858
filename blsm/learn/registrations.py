"""Registrations in the model topology, read from ``blsm-registration`` files, and their selection.

A registration is one scan's mesh brought into the template topology: ``vertices`` (V, 3) in
metres, world frame (Y up), and a ``meta`` JSON with the subject id, the pose id and the split
(``"train"`` or ``"test"``).  :func:`load_registrations` reads a folder of them into a
:class:`RegistrationSet`; :func:`spread_over_subjects` picks a subset that covers many subjects.

Used by the held-out evaluation (:mod:`blsm.learn.evaluate`), the SMPL-reimpl baseline's training
(:mod:`blsm.learn.smpl_reimpl`) and the pipeline (:mod:`blsm.learn.pipeline`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

__all__ = ["RegistrationSet", "load_registrations", "spread_over_subjects"]


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


def load_registrations(
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
