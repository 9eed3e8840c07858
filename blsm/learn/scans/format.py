"""Body scans with anatomical landmarks: the "blsm-scan" v1 file and the landmark operator A_lm.

The scan-fitting pipeline (thesis Sec. 5.4, Eqs. 5.13-5.15) registers the template to scans that
come with located landmarks (CAESAR: about 70 per scan). A scan file (``.npz``, format
``blsm-scan``, version 1) holds:

=================  ==============  ===========================================================
key                shape / dtype   meaning
=================  ==============  ===========================================================
format             str             ``"blsm-scan"``
format_version     int             1
vertices           (N, 3) float32  scan vertices, metres, world frame (Y up, facing +Z)
faces              (F, 3) int32    triangles; open borders (holes) allowed, no edge with > 2 faces
landmark_names     (L,) str        names from ``blsm/data/landmarks.yaml``
landmarks          (L, 3) float32  located landmarks, metres; a row of NaN = not located
meta               str             JSON: id, subject, pose id, source, phenotype, artefacts, ...
gt_points          (Vb, 3) float32 optional: true position of every BLSM template vertex on the
                                   clean posed body surface (synthetic scans only)
gt_angles          (47,) float32   optional: the true pose, radians
gt_global_orient   (3,) float32    optional: axis-angle, radians
gt_transl          (3,) float32    optional: metres
gt_joints          (J, 3) float32  optional: true BLSM joint positions of the posed body (the
                                   Anny bone head each BLSM joint was built from), metres
colors             (N, 3) uint8    optional: per-vertex sRGB colour (a textured scan, e.g. for
                                   markerless keypoints, :mod:`blsm.learn.markerless.keypoints`)
=================  ==============  ===========================================================

Colours are stored as uint8; :class:`Scan` accepts (N, 3) uint8 or float in [0, 1] (converted on
saving). OBJ / PLY meshes with vertex colours (trimesh's ``visual.vertex_colors``) keep them.

:func:`load_scan` also reads OBJ / PLY / GLB meshes (trimesh) with a landmark JSON file
``<stem>.landmarks.json`` beside them (or given explicitly): ``{name: [x, y, z]}``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm.io import read_versioned_npz, write_versioned_npz
from blsm.learn.scans.landmarks import LANDMARKS_YAML

FORMAT = "blsm-scan"
FORMAT_VERSION = 1
MESH_SUFFIXES = (".obj", ".ply", ".glb")
_GT_KEYS = ("gt_points", "gt_angles", "gt_global_orient", "gt_transl", "gt_joints")


@dataclass
class Scan:
    """One body scan (see the module docstring for units and frames).

    Attributes:
        vertices: (N, 3) float32 metres.
        faces: (F, 3) int32.
        landmark_names: L names from ``landmarks.yaml``.
        landmarks: (L, 3) float32 metres; NaN rows = not located.
        meta: JSON-able metadata (``id``, ``subject``, ``pose``, ``source``, ...).
        gt_points: (Vb, 3) float32 or None: ground-truth template correspondence.
        gt_angles: (47,) radians or None. gt_global_orient: (3,) or None. gt_transl: (3,) or None.
        gt_joints: (J, 3) float32 true BLSM joints, metres, or None.
        colors: (N, 3) uint8 (or float in [0, 1]) sRGB vertex colours, or None.
    """

    vertices: np.ndarray
    faces: np.ndarray
    landmark_names: list[str]
    landmarks: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)
    gt_points: np.ndarray | None = None
    gt_angles: np.ndarray | None = None
    gt_global_orient: np.ndarray | None = None
    gt_transl: np.ndarray | None = None
    gt_joints: np.ndarray | None = None
    colors: np.ndarray | None = None

    @property
    def located(self) -> np.ndarray:
        """(L,) bool: landmarks located on this scan (not NaN)."""
        return ~np.isnan(self.landmarks).any(axis=1)


# ----------------------------------------------------------------------------------------------
# Landmark table and A_lm


@lru_cache(maxsize=4)
def _read_table(
    path: str,
) -> tuple[tuple[str, ...], tuple[tuple[int, ...], ...], tuple[tuple[float, ...], ...]]:
    import yaml

    try:
        with open(path) as fh:
            data = yaml.safe_load(fh)
    except (OSError, yaml.YAMLError) as e:
        raise ValueError(f"{path}: cannot read landmark table ({e})") from None
    if not isinstance(data, dict) or not data:
        raise ValueError(f"{path}: landmark table must be a non-empty mapping name -> {{vertex: i}}")
    names, corners, weights = [], [], []
    for name, spec in data.items():
        if isinstance(spec, dict) and set(spec) == {"vertex"}:
            corners.append((int(spec["vertex"]),) * 3)
            weights.append((1.0, 0.0, 0.0))
        elif isinstance(spec, dict) and set(spec) == {"face", "bary"} and len(spec["bary"]) == 3:
            corners.append((-1 - int(spec["face"]), 0, 0))  # resolved against the model's faces
            weights.append(tuple(float(b) for b in spec["bary"]))
        else:
            raise ValueError(
                f"{path}: landmark {name!r} must be {{vertex: i}} or {{face: f, bary: [a, b, c]}}"
            )
        names.append(str(name))
    return tuple(names), tuple(corners), tuple(weights)


def landmark_names(path: str | Path = LANDMARKS_YAML) -> list[str]:
    """The L landmark names of the table, in file order."""
    return list(_read_table(str(path))[0])


def template_landmarks(
    model, path: str | Path = LANDMARKS_YAML
) -> tuple[list[str], torch.Tensor, torch.Tensor]:
    """The landmark table resolved on ``model``'s topology.

    Args:
        model: a :class:`blsm.BLSM` (its ``faces`` resolve ``{face, bary}`` entries).
        path: the YAML table.

    Returns:
        (names (L,), vertex indices (L, 3) long, barycentric weights (L, 3)): a ``{vertex: i}``
        landmark is ``(i, i, i)`` with weights ``(1, 0, 0)``.
    """
    names, corners, weights = _read_table(str(path))
    idx = torch.tensor(corners, dtype=torch.long)
    faces = model.faces.long().cpu()
    is_face = idx[:, 0] < 0
    if is_face.any():
        idx[is_face] = faces[-1 - idx[is_face, 0]]
    if idx.max() >= model.num_vertices:
        raise ValueError(f"{path}: a landmark vertex is >= the model's {model.num_vertices} vertices")
    return list(names), idx, torch.tensor(weights, dtype=model.template.dtype)


def landmark_points(vertices: torch.Tensor, model=None, path: str | Path = LANDMARKS_YAML) -> torch.Tensor:
    """The selection operator A_lm of Eq. 5.13: landmark points of bodies in BLSM topology.

    Args:
        vertices: (B, V, 3) or (V, 3) bodies in the template's topology, metres.
        model: needed only if the table has ``{face, bary}`` entries.
        path: the YAML table.

    Returns:
        (B, L, 3) (or (L, 3)) landmark points, in the table's order; differentiable.
    """
    names, corners, weights = _read_table(str(path))
    idx = torch.tensor(corners, dtype=torch.long, device=vertices.device)
    if (idx[:, 0] < 0).any():
        if model is None:
            raise ValueError(f"{path}: face landmarks need the model (pass model=)")
        _, idx, _ = template_landmarks(model, path)
        idx = idx.to(vertices.device)
    if vertices.shape[-1] != 3 or vertices.dim() not in (2, 3) or int(idx.max()) >= vertices.shape[-2]:
        raise ValueError(
            f"vertices must be (B, V, 3) in the template's topology, got {tuple(vertices.shape)}"
        )
    w = torch.tensor(weights, dtype=vertices.dtype, device=vertices.device)
    return (vertices[..., idx, :] * w[:, :, None]).sum(-2)  # (B, L, 3)


# ----------------------------------------------------------------------------------------------
# Checks


def non_manifold_edges(faces: np.ndarray) -> int:
    """Number of undirected edges shared by more than two faces."""
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return int((counts > 2).sum())


def check_scan(scan: Scan, where: str, require_landmarks: bool = False) -> None:
    """Raise a one-line ``ValueError`` starting with ``where`` if ``scan`` is not a valid scan."""
    v, f = scan.vertices, scan.faces
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"{where}: empty mesh or vertices not (N, 3) (got {v.shape})")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"{where}: empty mesh or faces not (F, 3) (got {f.shape})")
    if not np.isfinite(v).all():
        raise ValueError(f"{where}: {int((~np.isfinite(v)).any(1).sum())} vertices are NaN or inf")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"{where}: face indices outside [0, {len(v)})")
    bad = non_manifold_edges(f)
    if bad:
        raise ValueError(f"{where}: non-manifold mesh ({bad} edges shared by more than two faces)")
    lm = scan.landmarks
    if lm.ndim != 2 or lm.shape != (len(scan.landmark_names), 3):
        raise ValueError(
            f"{where}: landmarks must be (L, 3) with L = {len(scan.landmark_names)} names, got {lm.shape}"
        )
    nan_rows = np.isnan(lm).all(1)
    if not np.isfinite(lm[~nan_rows]).all():
        raise ValueError(f"{where}: landmarks hold NaN or inf values other than all-NaN rows")
    known = set(landmark_names())
    unknown = [n for n in scan.landmark_names if n not in known]
    if unknown:
        raise ValueError(f"{where}: unknown landmark names {unknown[:5]} (not in {LANDMARKS_YAML.name})")
    if len(set(scan.landmark_names)) != len(scan.landmark_names):
        raise ValueError(f"{where}: duplicate landmark names")
    if require_landmarks and (~nan_rows).sum() == 0:
        raise ValueError(f"{where}: scan has no located landmarks (require_landmarks=True)")
    for key in _GT_KEYS:
        val = getattr(scan, key)
        if val is not None and not np.isfinite(val).all():
            raise ValueError(f"{where}: {key} holds NaN or inf")
    if scan.colors is not None:
        c = np.asarray(scan.colors)
        if c.shape != (len(v), 3):
            raise ValueError(f"{where}: colors must be (N, 3) with N = {len(v)} vertices, got {c.shape}")
        if c.dtype != np.uint8 and not (np.isfinite(c).all() and c.min() >= 0 and c.max() <= 1):
            raise ValueError(f"{where}: float colors must be finite and in [0, 1]")


def colors_uint8(colors: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 sRGB colours from uint8 or float colours in [0, 1]."""
    c = np.asarray(colors)
    if c.dtype == np.uint8:
        return c
    return np.round(np.clip(c.astype(np.float64), 0.0, 1.0) * 255.0).astype(np.uint8)


# ----------------------------------------------------------------------------------------------
# Files


def save_scan(scan: Scan, path: str | Path) -> Path:
    """Write ``scan`` as a compressed "blsm-scan" v1 ``.npz`` (atomically); returns the path."""
    path = Path(path)
    check_scan(scan, str(path))
    arrays: dict[str, np.ndarray] = {
        "vertices": np.asarray(scan.vertices, np.float32),
        "faces": np.asarray(scan.faces, np.int32),
        "landmark_names": np.array(list(scan.landmark_names), dtype=str),
        "landmarks": np.asarray(scan.landmarks, np.float32),
        "meta": np.array(json.dumps(scan.meta)),
    }
    for key in _GT_KEYS:
        if getattr(scan, key) is not None:
            arrays[key] = np.asarray(getattr(scan, key), np.float32)
    if scan.colors is not None:
        arrays["colors"] = colors_uint8(scan.colors)
    return write_versioned_npz(path, FORMAT, FORMAT_VERSION, arrays)


def _load_npz(path: Path) -> Scan:
    data = read_versioned_npz(path, FORMAT, FORMAT_VERSION, "scan")
    for key in ("vertices", "faces", "landmark_names", "landmarks", "meta"):
        if key not in data:
            raise ValueError(f"{path}: missing array {key!r}")
    try:
        meta = json.loads(str(data["meta"]))
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: meta is not JSON ({e})") from None
    return Scan(
        vertices=data["vertices"].astype(np.float32),
        faces=data["faces"].astype(np.int32),
        landmark_names=[str(n) for n in data["landmark_names"]],
        landmarks=data["landmarks"].astype(np.float32).reshape(-1, 3),
        meta=meta,
        **{k: (data[k].astype(np.float32) if k in data else None) for k in _GT_KEYS},
        colors=data["colors"].astype(np.uint8) if "colors" in data else None,
    )


def _load_mesh(path: Path, landmarks: str | Path | None) -> Scan:
    import trimesh

    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:
        raise ValueError(f"{path}: unreadable mesh ({type(e).__name__}: {e})") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"{path}: no triangle mesh in the file")
    lm_path = Path(landmarks) if landmarks is not None else path.with_suffix(".landmarks.json")
    names: list[str] = []
    points = np.zeros((0, 3), np.float32)
    if lm_path.is_file():
        try:
            table = json.loads(lm_path.read_text())
            if not isinstance(table, dict):
                raise ValueError("not a mapping name -> [x, y, z]")
            names = [str(k) for k in table]
            points = np.array(
                [[np.nan] * 3 if v is None else v for v in table.values()], dtype=np.float32
            ).reshape(len(names), 3)
        except (OSError, ValueError, TypeError) as e:
            raise ValueError(f"{lm_path}: bad landmark file ({e})") from None
        # Checked here so that the error names this file, not the mesh (check_scan repeats it).
        partial = ~np.isfinite(points).all(1) & ~np.isnan(points).all(1)
        if partial.any():
            raise ValueError(f"{lm_path}: landmark {names[int(np.argmax(partial))]!r} holds NaN or inf "
                             "(write null for a landmark that was not located)")
        unknown = [n for n in names if n not in set(landmark_names())]
        if unknown:
            raise ValueError(f"{lm_path}: unknown landmark names {unknown[:5]} (not in {LANDMARKS_YAML.name})")
    elif landmarks is not None:
        raise ValueError(f"{lm_path}: landmark file does not exist")
    return Scan(
        vertices=np.asarray(mesh.vertices, np.float32),
        faces=np.asarray(mesh.faces, np.int32).reshape(-1, 3),
        landmark_names=names,
        landmarks=points,
        meta={"id": path.stem, "source": str(path)},
        colors=_mesh_colors(mesh),
    )


def _mesh_colors(mesh) -> np.ndarray | None:
    """(N, 3) uint8 vertex colours of a trimesh mesh, or None (no colours, or a texture/UV map)."""
    visual = getattr(mesh, "visual", None)
    if visual is None or getattr(visual, "kind", None) != "vertex":
        return None
    c = np.asarray(visual.vertex_colors)
    if c.ndim != 2 or len(c) != len(mesh.vertices) or c.shape[1] < 3:
        return None
    return np.ascontiguousarray(c[:, :3], dtype=np.uint8)


def load_scan(path: str | Path, landmarks: str | Path | None = None, require_landmarks: bool = False) -> Scan:
    """Read and check a scan: a "blsm-scan" ``.npz`` or an OBJ / PLY / GLB mesh with landmarks.

    Args:
        path: the scan file.
        landmarks: for meshes, a JSON file ``{name: [x, y, z] | null}``, metres; default
            ``<stem>.landmarks.json`` beside the mesh (a mesh without one has no landmarks).
        require_landmarks: raise if no landmark is located.

    Returns:
        The :class:`Scan`.

    Raises:
        ValueError: one line naming the file and the problem (unreadable, empty mesh, NaN/inf,
            face index out of range, non-manifold edge, unknown landmark, missing landmarks).
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: scan file does not exist")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        scan = _load_npz(path)
    elif suffix in MESH_SUFFIXES:
        scan = _load_mesh(path, landmarks)
    else:
        raise ValueError(f"{path}: unknown scan file type {suffix!r} (expected .npz, .obj, .ply or .glb)")
    check_scan(scan, str(path), require_landmarks=require_landmarks)
    return scan
