"""The spiral networks' precomputed operators for a BLSM model, cached per model file.

:func:`mesh_operators` returns, for the model's template (7002 vertices for the packaged model):

- the mesh hierarchy of Sec. 4.3.2 (:func:`recovery.mesh.sampling.build_levels`) made on the
  template posed in :data:`REFERENCE_ANGLES` (thesis Fig. 4.2: elbows, knees, hips, shoulders,
  wrists and ankles bent, so that quadric edge collapse keeps vertices around the joints);
- the spiral sequences of every level (:func:`recovery.mesh.spiral_sequences.spiral_sequences`), with the
  level's ring count (Table 4.1's kernel size) and fixed length;
- the **keypoint regressor** ``J`` (K, V): keypoints as a linear function of the vertices. The
  model's surface keypoints are already barycentric combinations of vertices (copied exactly);
  its joint keypoints (bone heads) come from the skeleton, so for each a non-negative, sum-to-one
  combination of nearby vertices is fitted to BLSM bodies of the model's population in prior poses
  (SMPL's ``J_regressor`` made the same way); the fit's held-out error is stored.

Everything is written to ``cache_dir/mesh_ops-<hash>.npz``, the hash covering the model file's
SHA-256, the settings and :data:`OPS_VERSION`; a changed model file or setting builds a new file.
Networks copy what they need into buffers, so a trained checkpoint never depends on the cache.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from recovery.mesh.sampling import Level, build_levels
from recovery.mesh.spiral_sequences import spiral_sequences

OPS_VERSION = 1

REFERENCE_ANGLES: dict[str, float] = {
    "shoulder_l.abduct": 0.8, "shoulder_r.abduct": 0.8, "shoulder_l.flex": 0.4, "shoulder_r.flex": 0.4,
    "elbow_l.flex": 1.2, "elbow_r.flex": 1.2, "wrist_l.flex": 0.5, "wrist_r.flex": 0.5,
    "hip_l.flex": 0.6, "hip_r.flex": 0.6, "hip_l.abduct": 0.3, "hip_r.abduct": 0.3,
    "knee_l.flex": 1.0, "knee_r.flex": 1.0, "ankle_l.plantarflex": 0.3, "ankle_r.plantarflex": 0.3,
    "spine_02.flex": 0.2, "neck.flex": 0.3,
}
"""The reference pose of the down-sampling (radians, each clamped to 90 % of its limit; sign
towards the limit of the larger magnitude): bent limbs curve the surface at the joints, so the
quadric error keeps vertices there (thesis Fig. 4.2)."""


@dataclass(frozen=True)
class MeshOpsSettings:
    """How the operators are built (part of the cache key).

    Attributes:
        factors: vertex reduction per level (thesis: 4, 2, 2, 2).
        rings: spiral rings per convolution level 0..len(factors)-1 (Table 4.1 kernel sizes 2, 1, 1, 1).
        lengths: fixed spiral length per level (1 + the rings' typical vertex count; padded with -1).
        regressor_samples: posed bodies the joint regressor is fitted on.
        regressor_support: candidate vertices per joint (nearest on the rest template, on the
            joint's bone, its parent and its children).
    """

    factors: tuple[float, ...] = (4, 2, 2, 2)
    rings: tuple[int, ...] = (2, 1, 1, 1)
    lengths: tuple[int, ...] = (25, 9, 9, 9)
    regressor_samples: int = 400
    regressor_support: int = 128

    def __post_init__(self) -> None:
        # one type per field, so that a config read back from a checkpoint (factors 4.0) keys the same cache as YAML's 4
        object.__setattr__(self, "factors", tuple(float(f) for f in self.factors))
        object.__setattr__(self, "rings", tuple(int(r) for r in self.rings))
        object.__setattr__(self, "lengths", tuple(int(n) for n in self.lengths))
        object.__setattr__(self, "regressor_samples", int(self.regressor_samples))
        object.__setattr__(self, "regressor_support", int(self.regressor_support))
        if not (len(self.rings) == len(self.lengths) == len(self.factors)):
            raise ValueError("factors, rings and lengths need one entry per level")
        if min(self.rings) < 1 or min(self.lengths) < 1 or min(self.factors) <= 1:
            raise ValueError("rings and lengths must be >= 1 and factors > 1")


@dataclass
class MeshOperators:
    """Everything the spiral networks need about the template (module docstring).

    Attributes:
        levels: the down/up-sampling steps (``len(factors)`` of them).
        spirals: spiral indices per level 0..len(factors)-1, (n_l, L_l), -1 = padding.
        faces: triangles per level 0..len(factors) (level 0 is the template's).
        reference: (V, 3) the template in the reference pose (metres).
        regressor: (K, V) keypoints = regressor @ vertices.
        keypoint_names: the K names (the model's).
        regressor_error_mm: the joint regressor's mean error on held-out posed bodies.
        model_sha256: the model file these were made for.
    """

    levels: list[Level]
    spirals: list[np.ndarray]
    faces: list[np.ndarray]
    reference: np.ndarray
    regressor: np.ndarray
    keypoint_names: list[str]
    regressor_error_mm: float
    model_sha256: str

    @property
    def sizes(self) -> list[int]:
        """Vertices per level 0..len(levels)."""
        return [len(self.reference)] + [len(lv.down) for lv in self.levels]


def reference_angles(body: torch.nn.Module) -> torch.Tensor:
    """(47,) the reference pose of :data:`REFERENCE_ANGLES`, inside the model's limits."""
    lim = body.dof_limits.double()
    out = torch.zeros(body.num_dofs, dtype=torch.float64)
    for name, value in REFERENCE_ANGLES.items():
        if name not in body.dof_names:
            continue
        i = body.dof_names.index(name)
        lo, hi = float(lim[i, 0]), float(lim[i, 1])
        sign = 1.0 if abs(hi) >= abs(lo) else -1.0
        out[i] = min(value, 0.9 * max(abs(lo), abs(hi))) * sign
    return out.clamp(lim[:, 0] * 0.9, lim[:, 1] * 0.9)


def _posed_bodies(body: torch.nn.Module, n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(n, V, 3) vertices and (n, J, 3) joints of population members in prior poses (float64)."""
    from blsm.mocap.prior import DEFAULT_PRIOR, load_prior

    g = torch.Generator().manual_seed(seed)
    prior = load_prior(DEFAULT_PRIOR)
    pose = prior.sample(n, g).to(body.template.dtype)
    who = torch.randint(0, body.population_bone.shape[0], (n,), generator=g)
    with torch.no_grad():
        out = body(pose=pose, bone=body.population_bone[who], shape=body.population_shape[who])
    return out.vertices.double(), out.joints.double()


def fit_keypoint_regressor(body: torch.nn.Module, samples: int, support: int, seed: int = 0) -> tuple[np.ndarray, float]:
    """The (K, V) keypoint regressor of the module docstring and its held-out joint error (mm)."""
    from scipy.optimize import nnls

    names = list(body.keypoint_names)
    nv = body.num_vertices
    reg = np.zeros((len(names), nv))
    kv = body.keypoint_vertices.numpy()
    kw = body.keypoint_weights.numpy()
    kj = body.keypoint_joint.numpy()
    verts, joints = _posed_bodies(body, samples, seed)
    tv, tj = _posed_bodies(body, max(samples // 4, 8), seed + 1)
    rest = body.template.double().numpy()
    heads = body.heads.double().numpy()
    vb = body.vertex_bones.numpy()
    parents = body.parents
    errs = []
    for k in range(len(names)):
        j = int(kj[k])
        if j < 0:
            np.add.at(reg[k], kv[k], kw[k])
            continue
        bones = {j, *(c for c, p in enumerate(parents) if p == j)} | ({parents[j]} if parents[j] >= 0 else set())
        cand = np.flatnonzero(np.isin(vb, list(bones)))
        if len(cand) < 3:
            cand = np.arange(nv)
        cand = cand[np.argsort(np.linalg.norm(rest[cand] - heads[j], axis=1))[:support]]
        a = verts[:, cand].permute(0, 2, 1).reshape(-1, len(cand)).numpy()  # (n*3, c)
        b = joints[:, j].reshape(-1).numpy()
        w_sum = 100.0  # the sum-to-one row, weighted so it holds to about 1e-4
        a = np.vstack([a, np.full((1, len(cand)), w_sum)])
        b = np.concatenate([b, [w_sum]])
        x, _ = nnls(a, b, maxiter=50 * len(cand))
        reg[k, cand] = x / max(x.sum(), 1e-12)
        pred = torch.einsum("v,nvc->nc", torch.from_numpy(reg[k]), tv)
        errs.append(float((pred - tj[:, j]).norm(dim=-1).mean()) * 1000)
    return reg, float(np.mean(errs)) if errs else 0.0


def mesh_hierarchy(positions: np.ndarray, faces: np.ndarray, settings: MeshOpsSettings) -> MeshOperators:
    """Levels and spirals of any mesh (no keypoint regressor: an empty (0, V) one)."""
    ref = np.asarray(positions, dtype=np.float64)
    faces0 = np.asarray(faces, dtype=np.int64)
    levels = build_levels(ref, faces0, tuple(settings.factors))
    pos, fcs, spirals, all_faces = ref, faces0, [], [faces0]
    for i, lv in enumerate(levels):
        spirals.append(spiral_sequences(pos, fcs, settings.rings[i], settings.lengths[i]))
        pos, fcs = pos[lv.down], lv.faces
        all_faces.append(fcs)
    return MeshOperators(levels=levels, spirals=spirals, faces=all_faces, reference=ref.astype(np.float32),
                         regressor=np.zeros((0, len(ref)), np.float32), keypoint_names=[],
                         regressor_error_mm=0.0, model_sha256="")


def build_operators(body: torch.nn.Module, settings: MeshOpsSettings, model_sha256: str = "") -> MeshOperators:
    """Build every operator for ``body`` (about 5 s for the packaged model)."""
    with torch.no_grad():
        ref = body(angles=reference_angles(body)[None].to(body.template.dtype)).vertices[0].double().numpy()
    ops = mesh_hierarchy(ref, body.faces.numpy(), settings)
    reg, err = fit_keypoint_regressor(body, settings.regressor_samples, settings.regressor_support)
    ops.regressor, ops.keypoint_names = reg.astype(np.float32), list(body.keypoint_names)
    ops.regressor_error_mm, ops.model_sha256 = err, model_sha256
    return ops


def _key(model_sha256: str, settings: MeshOpsSettings) -> str:
    text = json.dumps({"v": OPS_VERSION, "model": model_sha256, "settings": dataclasses.asdict(settings)}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def save_operators(ops: MeshOperators, path: Path) -> None:
    from blsm.io import atomic_write

    arrays: dict[str, Any] = {"reference": ops.reference, "regressor": ops.regressor}
    for i, lv in enumerate(ops.levels):
        arrays[f"down_{i}"], arrays[f"up_index_{i}"], arrays[f"up_weight_{i}"] = lv.down, lv.up_index, lv.up_weight
    for i, f in enumerate(ops.faces):
        arrays[f"faces_{i}"] = f
    for i, s in enumerate(ops.spirals):
        arrays[f"spiral_{i}"] = s
    meta = {"levels": len(ops.levels), "keypoint_names": ops.keypoint_names,
            "regressor_error_mm": ops.regressor_error_mm, "model_sha256": ops.model_sha256}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "wb") as fh:
        np.savez(fh, **arrays)


def read_operators(path: Path) -> MeshOperators:
    with np.load(path) as z:
        meta = json.loads(bytes(z["meta"]).decode())
        n = meta["levels"]
        levels = [Level(down=z[f"down_{i}"], up_index=z[f"up_index_{i}"], up_weight=z[f"up_weight_{i}"],
                        faces=z[f"faces_{i + 1}"]) for i in range(n)]
        return MeshOperators(levels=levels, spirals=[z[f"spiral_{i}"] for i in range(n)],
                             faces=[z[f"faces_{i}"] for i in range(n + 1)], reference=z["reference"],
                             regressor=z["regressor"], keypoint_names=meta["keypoint_names"],
                             regressor_error_mm=meta["regressor_error_mm"], model_sha256=meta["model_sha256"])


def mesh_operators(model_path: str | Path | None = None, cache_dir: str | Path = "out/cache/mesh",
                   settings: MeshOpsSettings | None = None, log: Any = print) -> MeshOperators:
    """The operators of a BLSM model file (default: the packaged one), from the cache or built."""
    import blsm
    from blsm.io import sha256_file
    from blsm.model import DEFAULT_MODEL

    settings = settings or MeshOpsSettings()
    path = Path(model_path) if model_path else DEFAULT_MODEL
    sha = sha256_file(path)
    cache = Path(cache_dir) / f"mesh_ops-{_key(sha, settings)}.npz"
    if cache.is_file():
        try:
            return read_operators(cache)
        except Exception as exc:  # noqa: BLE001 - a damaged cache is rebuilt, and said so
            log(f"[mesh] {cache}: unreadable ({type(exc).__name__}); rebuilding")
    ops = build_operators(blsm.load(path), settings, sha)
    save_operators(ops, cache)
    log(f"[mesh] operators for {path.name}: levels {ops.sizes}, joint regressor {ops.regressor_error_mm:.2f} mm -> {cache}")
    return ops
