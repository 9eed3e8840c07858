"""Exact occupancy of a body mesh: which points are inside, and how far from the surface.

The ground truth of LEAP (:mod:`blsm.leap`), of the generator's close placement
(:mod:`synth.close`) and of its contact and occupancy labels. A point is inside a triangle mesh
where its **generalised winding number** (Jacobson, Kavan and Sorkine-Hornung 2013) is above
one half: the solid angle the mesh subtends at the point over 4 pi, which is exactly 1 inside and 0
outside a closed, consistently oriented mesh and degrades gracefully where a mesh has small holes
(the eyes and mouth of a body scan). It is computed by libigl's fast winding number (Barill et al.
2018: a tree of the triangles with far clusters replaced by dipole expansions), accurate to well
under the 1/2 threshold away from the surface (the default here is libigl's exact hierarchical
evaluation; the fast one is an option, and agreed on all of 100,000 LEAP-style query points around
an Anny body). Distances are libigl's exact point-triangle distances over an AABB tree, signed by
that winding number.

Units are the mesh's (metres in this project). Inputs are converted to what libigl takes
(float64 points and vertices, int64 faces).
"""

from __future__ import annotations

import numpy as np

from blsm.mesh import barycentric

NEAR_SIGMA_M = 0.01
"""Standard deviation (metres) of the points :func:`sample_points` draws around the surface."""
BOX_PADDING = 0.1
"""The uniform points of :func:`sample_points` fill the mesh's box grown by this share of its size
on each side (LEAP Sec. 6, "a scaled bounding box around the human body (10 % padding)")."""


def _arrays(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, ...]:
    p = np.ascontiguousarray(np.asarray(points, np.float64).reshape(-1, 3))
    v = np.ascontiguousarray(np.asarray(vertices, np.float64))
    f = np.ascontiguousarray(np.asarray(faces, np.int64))
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"a mesh is (V, 3) vertices and (F, 3) faces, got {v.shape} and {f.shape}")
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"faces index vertices 0..{len(v) - 1}, got {f.min()}..{f.max()}")
    return p, v, f


def winding_numbers(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, exact: bool = True) -> np.ndarray:
    """(N,) generalised winding numbers of ``points`` (N, 3) with respect to the mesh: exact
    (libigl's hierarchical evaluation, Jacobson et al. 2013) or, with ``exact=False``, the fast
    dipole approximation (Barill et al. 2018; about 5 times faster)."""
    import igl

    p, v, f = _arrays(points, vertices, faces)
    if not len(p):
        return np.zeros(0)
    w = igl.winding_number(v, f, p) if exact else igl.fast_winding_number(v, f, p)
    return np.asarray(w, np.float64)


def inside(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, exact: bool = True) -> np.ndarray:
    """(N,) bool: whether each point is inside the mesh (winding number above 1/2)."""
    return winding_numbers(points, vertices, faces, exact) > 0.5


def signed_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                    exact: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(N,) signed distances of ``points`` to the mesh's surface (negative inside, by the winding
    number, exact or fast as in :func:`winding_numbers`) and (N,) the index of the nearest face."""
    import igl

    p, v, f = _arrays(points, vertices, faces)
    if not len(p):
        return np.zeros(0), np.zeros(0, np.int64)
    kind = igl.SIGNED_DISTANCE_TYPE_WINDING_NUMBER if exact else igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER
    s, i, _, _ = igl.signed_distance(p, v, f, kind)
    return np.asarray(s, np.float64), np.asarray(i, np.int64)


def distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, upper: float = np.inf) -> np.ndarray:
    """(N,) unsigned distances of ``points`` to the mesh's surface; with ``upper``, points farther
    than it get ``upper`` (the search stops there: faster)."""
    import igl

    p, v, f = _arrays(points, vertices, faces)
    if not len(p):
        return np.zeros(0)
    if np.isfinite(upper):
        s = igl.signed_distance(p, v, f, igl.SIGNED_DISTANCE_TYPE_UNSIGNED, 0.0, float(upper))[0]
        return np.where(np.isnan(s), upper, np.minimum(np.abs(s), upper))  # beyond the bound: NaN
    return np.abs(np.asarray(igl.signed_distance(p, v, f, igl.SIGNED_DISTANCE_TYPE_UNSIGNED)[0], np.float64))


def surface_points(vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) points uniform on the mesh's surface (faces drawn by area, then a uniform point of each)."""
    v = np.asarray(vertices, np.float64)
    tri = v[np.asarray(faces)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    fi = rng.choice(len(tri), size=n, p=area / area.sum())
    a, b = rng.uniform(size=(2, n))
    flip = a + b > 1.0
    a, b = np.where(flip, 1.0 - a, a), np.where(flip, 1.0 - b, b)
    t = tri[fi]
    return t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0])


def sample_points(vertices: np.ndarray, faces: np.ndarray, n_near: int, n_uniform: int, rng: np.random.Generator,
                  sigma: float = NEAR_SIGMA_M, padding: float = BOX_PADDING) -> np.ndarray:
    """Query points as LEAP (Sec. 6) and NASA draw them: ``n_near`` surface points
    (:func:`surface_points`) moved by N(0, ``sigma``^2) per axis, then ``n_uniform`` uniform in the
    mesh's box grown by ``padding`` of its size on each side; (n_near + n_uniform, 3)."""
    v = np.asarray(vertices, np.float64)
    near = surface_points(v, faces, n_near, rng) + rng.normal(0.0, sigma, (n_near, 3))
    lo, hi = v.min(0), v.max(0)
    pad = padding * (hi - lo)
    uniform = rng.uniform(lo - pad, hi + pad, (n_uniform, 3))
    return np.concatenate([near, uniform])


class MeshSDF:
    """The signed distance to one closed mesh, queried many times: libigl's AABB tree built once,
    the sign from angle-weighted pseudonormals (Baerentzen and Aanaes 2005: the normal of the
    nearest face, or the sum of the two faces' normals at an edge, or the angle-weighted sum at a
    vertex), which is exact for a closed, consistently oriented, manifold mesh; no per-call set-up.

    Raises:
        ValueError: where an edge does not join exactly two faces (not closed and manifold).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        import igl

        _, self.v, self.f = _arrays(np.zeros((0, 3)), vertices, faces)
        tri = self.v[self.f]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.face_n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
        vn = np.zeros_like(self.v)
        for k in range(3):  # the angle of each face at its k-th corner
            e1, e2 = tri[:, (k + 1) % 3] - tri[:, k], tri[:, (k + 2) % 3] - tri[:, k]
            cos = (e1 * e2).sum(1) / np.maximum(np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1), 1e-30)
            np.add.at(vn, self.f[:, k], np.arccos(np.clip(cos, -1.0, 1.0))[:, None] * self.face_n)
        self.vertex_n = vn
        # Edge k of a face joins corners (k + 1) % 3 and (k + 2) % 3 (opposite corner k).
        edges = np.stack([np.sort(self.f[:, [(k + 1) % 3, (k + 2) % 3]], axis=1) for k in range(3)], 1).reshape(-1, 2)
        code = edges[:, 0] * len(self.v) + edges[:, 1]  # one integer an edge: a 1-D unique is fast
        key, inv, count = np.unique(code, return_inverse=True, return_counts=True)
        if (count != 2).any():
            raise ValueError(f"the mesh is not closed and manifold: {int((count != 2).sum())} edges without two faces")
        en = np.zeros((len(key), 3))
        np.add.at(en, inv.reshape(-1), np.repeat(self.face_n, 3, axis=0))
        self.edge_n = en[inv.reshape(-1, 3)]  # (F, 3, 3): per face, per opposite corner
        self.tree = igl.AABB()
        self.tree.init(self.v, self.f)

    def __call__(self, points: np.ndarray, eps: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
        """(N,) signed distances of ``points`` (negative inside) and (N,) the nearest faces."""
        p = np.ascontiguousarray(np.asarray(points, np.float64).reshape(-1, 3))
        if not len(p):
            return np.zeros(0), np.zeros(0, np.int64)
        d2, fi, c = self.tree.squared_distance(self.v, self.f, p)
        fi = np.asarray(fi, np.int64)
        tri = self.v[self.f[fi]]
        bary = barycentric(tri, c)  # of the nearest point: which feature (face, edge, vertex) it lies on
        zero = bary <= eps
        normal = self.face_n[fi].copy()
        on_edge = zero.sum(1) == 1
        k = np.argmax(zero, axis=1)
        normal[on_edge] = self.edge_n[fi[on_edge], k[on_edge]]
        on_vertex = zero.sum(1) >= 2
        corner = np.argmax(~zero, axis=1)  # the one corner not at zero
        normal[on_vertex] = self.vertex_n[self.f[fi[on_vertex], corner[on_vertex]]]
        sign = np.where(((p - c) * normal).sum(1) < 0.0, -1.0, 1.0)
        return sign * np.sqrt(np.maximum(d2, 0.0)), fi
