"""The spiral networks' precomputed operators for a BLSM model, cached per model file.

:func:`mesh_operators` returns, for the model's template (7002 vertices for the packaged model):

- the mesh hierarchy of Sec. 4.3.2 and the spiral sequences of every level
  (:func:`blsm.spiral.hierarchy.mesh_hierarchy`), made on the template posed in
  :data:`blsm.spiral.hierarchy.REFERENCE_ANGLES` (thesis Fig. 4.2);
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
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm.spiral.hierarchy import MeshOperators, MeshOpsSettings, body_hierarchy
from blsm.spiral.sampling import Level

OPS_VERSION = 1


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


def build_operators(body: torch.nn.Module, settings: MeshOpsSettings, model_sha256: str = "") -> MeshOperators:
    """Build every operator for ``body`` (about 5 s for the packaged model)."""
    ops = body_hierarchy(body, settings)
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
