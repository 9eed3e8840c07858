"""Surfaces from LEAP (issue 55, Table 2's Chamfer and the figure of reconstructed bodies): the
occupancy on a grid over the body's box, its 0.5 level set by marching cubes, and the Chamfer
distance to the true mesh.

The true mesh of a test body is BLSM's own: the subject's template (its population row's bone and
shape coefficients, Eq. 15) skinned by the body's transforms ``B`` (Eq. 12), the mesh whose exact
winding number gave the occupancy labels (:mod:`blsm.leap.data`).
"""

from __future__ import annotations

import numpy as np
import torch

from blsm import occupancy
from blsm.leap.data import subject_templates


def true_meshes(model: torch.nn.Module, B: np.ndarray, subjects: np.ndarray) -> np.ndarray:
    """(n, V, 3) the posed BLSM vertices of bodies with transforms ``B`` (n, K, 3, 4) and population
    rows ``subjects`` (n,)."""
    rest = subject_templates(model, subjects)
    with torch.no_grad():
        Bt = torch.as_tensor(B, dtype=rest.dtype)
        posed = torch.einsum("vk,bkij,bvj->bvi", model.weights, Bt[..., :3], rest)
        posed = posed + torch.einsum("vk,bki->bvi", model.weights, Bt[..., 3])
    return posed.numpy()


def grid_box(vertices: np.ndarray, grow: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """The body's box grown by ``grow`` of its size on every side (the query points' box)."""
    lo, hi = vertices.min(0), vertices.max(0)
    pad = grow * (hi - lo)
    return lo - pad, hi + pad


@torch.no_grad()
def occupancy_grid(leap: torch.nn.Module, B: np.ndarray, lo: np.ndarray, hi: np.ndarray, res: int,
                   chunk: int = 65536) -> np.ndarray:
    """(res, res, res) LEAP's occupancy probability at the grid's nodes, ``[i, j, k]`` at
    ``lo + (i, j, k) (hi - lo) / (res - 1)``, for one body ``B`` (K, 3, 4)."""
    leap.eval()
    axes = [np.linspace(lo[c], hi[c], res, dtype=np.float32) for c in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    Bt = torch.as_tensor(B, dtype=torch.float32)[None]
    out = np.empty(len(pts), np.float32)
    for s in range(0, len(pts), chunk):
        x = torch.from_numpy(pts[s : s + chunk])[None]
        out[s : s + chunk] = torch.sigmoid(leap(Bt, x)["logits"][0]).numpy()
    return out.reshape(res, res, res)


def reconstruct(leap: torch.nn.Module, B: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                res: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """LEAP's surface of one body: the 0.5 level set of :func:`occupancy_grid` by marching cubes,
    ``(vertices (N, 3), faces (F, 3))`` in the body's frame; empty arrays when nothing is inside."""
    from skimage.measure import marching_cubes

    grid = occupancy_grid(leap, B, lo, hi, res)
    if grid.max() < 0.5 or grid.min() >= 0.5:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    verts, faces, _, _ = marching_cubes(grid, 0.5, spacing=tuple((hi - lo) / (res - 1)))
    return verts + lo, faces[:, ::-1].astype(np.int64)  # outward: skimage orients them inward where the inside is high


def surface_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N,) the exact distance of ``points`` to the triangle mesh (libigl's AABB tree)."""
    import igl

    v, f = np.ascontiguousarray(vertices, np.float64), np.ascontiguousarray(faces, np.int64)
    d2, _, _ = igl.point_mesh_squared_distance(np.ascontiguousarray(points, np.float64), v, f)
    return np.sqrt(np.maximum(d2, 0.0))


def chamfer(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray], n: int,
            rng: np.random.Generator) -> float:
    """The symmetric Chamfer distance (metres) of two meshes: ``n`` points drawn uniformly on each
    surface, the mean of their exact distances to the other surface, averaged over both directions
    (ONet's "Chamfer-L1"); ``inf`` when ``a`` is empty."""
    if not len(a[1]):
        return float("inf")
    pa = occupancy.sample_points(a[0], a[1], n, 0, rng, sigma=0.0)
    pb = occupancy.sample_points(b[0], b[1], n, 0, rng, sigma=0.0)
    return 0.5 * float(surface_distance(pa, *b).mean() + surface_distance(pb, *a).mean())
