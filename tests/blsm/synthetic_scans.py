"""Synthetic scans of the packaged model for the registration tests (rest or posed, noisy, with holes)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from blsm.learn.registration.landmark_fit import LandmarkSelection


def fps_vertices(template: torch.Tensor, n: int) -> np.ndarray:
    """(n,) template vertex indices by farthest-point sampling from the top of the head."""
    v = template.double().numpy()
    idx = [int(np.argmax(v[:, 1]))]
    d = np.linalg.norm(v - v[idx[0]], axis=1)
    for _ in range(n - 1):
        i = int(np.argmax(d))
        idx.append(i)
        d = np.minimum(d, np.linalg.norm(v - v[i], axis=1))
    return np.array(idx)


def subdivide(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One midpoint subdivision: (V, 3), (F, 3) -> (V + E, 3), (4F, 3)."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, inv = np.unique(e, axis=0, return_inverse=True)
    mid = inv.reshape(3, -1).T + len(vertices)  # (F, 3) midpoints of edges 01, 12, 20
    verts = np.concatenate([vertices, 0.5 * (vertices[uniq[:, 0]] + vertices[uniq[:, 1]])])
    a, b, c = faces.T
    ab, bc, ca = mid.T
    new = np.concatenate([np.stack(t, 1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return verts, new


@dataclass
class SynthScan:
    vertices: np.ndarray
    faces: np.ndarray
    landmark_names: list
    landmarks: np.ndarray
    meta: dict
    gt_points: np.ndarray


def synthetic_scan(model, gen: torch.Generator, posed: bool, selection: LandmarkSelection,
                   noise: float = 0.001, lm_noise: float = 0.002, holes: bool = True) -> SynthScan:
    """A body of the model's population, rest or posed by the packaged CMU prior, subdivided once,
    with ``noise`` metres of Gaussian vertex noise, holes at the soles and armpits, and landmarks at
    the posed ``selection`` points (+ ``lm_noise``). ``gt_points`` are the clean posed vertices."""
    from blsm.mocap import prior as prior_mod

    k = int(torch.randint(0, model.population_bone.shape[0], (1,), generator=gen))
    go = (torch.rand(1, 3, generator=gen) - 0.5) * 0.6
    tr = torch.rand(1, 3, generator=gen) - 0.5
    kw = {}
    if posed:
        prior = prior_mod.load_prior(Path(prior_mod.__file__).parents[1] / "data" / "pose_prior_cmu.npz")
        seed = int(torch.randint(0, 1 << 30, (1,), generator=gen))
        kw["pose"] = prior.sample(1, generator=torch.Generator().manual_seed(seed)).to(model.template.dtype)
    with torch.no_grad():
        out = model(bone=model.population_bone[k:k + 1], shape=model.population_shape[k:k + 1],
                    global_orient=go.to(model.template.dtype), transl=tr.to(model.template.dtype), **kw)
    gt = out.vertices[0].double().numpy()
    faces = model.faces.numpy()
    t = model.template.double().numpy()
    keep = np.ones(len(faces), bool)
    if holes:
        bad = t[:, 1] < t[:, 1].min() + 0.02  # soles
        for sx in (1, -1):
            k_arm = int(np.argmin(np.linalg.norm(t - np.array([sx * 0.17, 0.28, 0.0]), axis=1)))
            bad |= np.linalg.norm(t - t[k_arm], axis=1) < 0.03  # armpits
        keep = ~bad[faces].any(1)
    used = np.unique(faces[keep])
    remap = -np.ones(len(gt), int)
    remap[used] = np.arange(len(used))
    v, f = subdivide(gt[used], remap[faces[keep]])
    rng = np.random.default_rng(int(torch.randint(0, 1 << 30, (1,), generator=gen)))
    v = v + rng.normal(0, noise, v.shape)
    lms = selection.select(torch.as_tensor(gt)[None])[0].numpy()
    lms = lms + rng.normal(0, lm_noise, lms.shape)
    return SynthScan(v.astype(np.float32), f.astype(np.int32), list(selection.names),
                     lms.astype(np.float32), {"id": "posed" if posed else "rest"}, gt.astype(np.float32))


def write_scan_npz(scan: SynthScan, path: Path, **override) -> Path:
    arrays = dict(format=np.array("blsm-scan"), format_version=np.array(1), vertices=scan.vertices,
                  faces=scan.faces, landmark_names=np.array(scan.landmark_names), landmarks=scan.landmarks,
                  meta=np.array(json.dumps(scan.meta)), gt_points=scan.gt_points)
    arrays.update(override)
    np.savez(path, **arrays)
    return path
