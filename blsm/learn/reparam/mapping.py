"""Reparameterising a statistical body model to a new template topology (thesis ch. 3).

Pure numpy / scipy functions; :mod:`blsm.learn.reparam.model` builds a whole BLSM model file with
them and :mod:`blsm.learn.reparam.evaluate` evaluates the result as thesis Sec. 3.4 does.

- :func:`closest_points`: exact vertex-to-surface correspondences (face, barycentrics, distance) of
  points on a triangle mesh (Sec. 3.3.2); a KD-tree of face centroids bounds the candidate faces so
  the result is the true closest point, not an approximation.
- :func:`mapping_matrix`: W' (N2 x N1, Eq. 3.7) with the barycentrics of each new vertex in its
  row; :func:`block_matrix` the 3N2 x 3N1 W of Sec. 3.3.2 (``W = W' (x) I_3``). Every per-vertex
  array is mapped with W' row by row (``(N1, C) -> (N2, C)``), which is W applied to the stacked
  ``[x_1, y_1, z_1, ...]`` vector.
- :func:`shape_space_eq35`: Eq. 3.5, ``Sigma_2 = W Sigma_1 W^T + (mu_2 - W mu_1)(mu_2 - W mu_1)^T``,
  in low rank: ``Sigma_1 = U S^2 U^T`` is the model's scaled PCA basis (metres per standard
  deviation, so ``Sigma_1 = P^T P``), and ``Sigma_2 = M M^T`` with ``M = [W U S, mu_2 - W mu_1]``
  (3N2 x (K + 1)); the thin SVD of M gives the principal components of Sigma_2 without forming a
  dense 3N2 x 3N2 matrix.
- :func:`align_template`: Sec. 3.3.2 assumes the new template "non-rigidly aligned" to the old
  one. Here a rigid (or rigid + scale) ICP onto the old surface; a non-rigid alignment is out of
  scope: a template that is a remesh or a subdivision of the model's surface is already on it.

Units: metres; vertex arrays (N, 3), Y up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

ALIGN_MODES = ("auto", "none", "rigid", "similarity")


@dataclass
class Correspondence:
    """Closest points of N2 query points on a mesh of N1 vertices (Sec. 3.3.2).

    Attributes:
        face: (N2,) index of the closest face.
        corners: (N2, 3) the face's vertex indices (a, b, c).
        bary: (N2, 3) barycentric coordinates (u, v, w) of the closest point, >= 0, summing to 1.
        distance: (N2,) distance in metres from the query point to its closest point.
    """

    face: np.ndarray
    corners: np.ndarray
    bary: np.ndarray
    distance: np.ndarray

    def points(self, vertices: np.ndarray) -> np.ndarray:
        """(N2, C) the closest points (or any per-vertex quantity) interpolated: ``W' vertices``."""
        return np.einsum("nk,nkc->nc", self.bary, vertices[self.corners])


def closest_point_triangle(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Barycentrics of the closest point to ``p`` on triangle (a, b, c), exactly (Voronoi regions).

    Ericson, *Real-Time Collision Detection*, Sec. 5.1.5, vectorised; a degenerate triangle falls to
    one of its edges or corners.

    Args:
        p, a, b, c: (M, 3) points and triangle corners.

    Returns:
        (M, 3) barycentrics (u, v, w), >= 0, summing to 1; the point is ``u a + v b + w c``.
    """
    p, a, b, c = (np.asarray(t, dtype=np.float64) for t in (p, a, b, c))
    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c

    def dot(x, y):
        return np.einsum("mi,mi->m", x, y)

    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    out = np.empty((len(p), 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v, w = vb / denom, vc / denom
        out[:] = np.stack([1.0 - v - w, v, w], 1)  # interior (the case when none below holds)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        t_ac = d2 / (d2 - d6)
        t_ab = d1 / (d1 - d3)
    one, zero = np.ones(len(p)), np.zeros(len(p))
    # Ericson tests the regions in this order; assigning in reverse lets the first match win.
    regions = [
        ((d1 <= 0) & (d2 <= 0), (one, zero, zero)),
        ((d3 >= 0) & (d4 <= d3), (zero, one, zero)),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), (1 - t_ab, t_ab, zero)),
        ((d6 >= 0) & (d5 <= d6), (zero, zero, one)),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), (1 - t_ac, zero, t_ac)),
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), (zero, 1 - t_bc, t_bc)),
    ]
    for mask, (u_, v_, w_) in reversed(regions):
        out[mask] = np.stack([u_, v_, w_], 1)[mask]
    bad = ~np.isfinite(out).all(1)
    if bad.any():  # a zero-area triangle seen from its interior test: take the nearest corner
        d = np.stack([np.linalg.norm(p - q, axis=1) for q in (a, b, c)], 1)[bad]
        out[bad] = np.eye(3)[d.argmin(1)]
    return np.clip(out, 0.0, 1.0) / np.clip(out, 0.0, 1.0).sum(1, keepdims=True)


def _best_of(pts, tri, pidx, fidx, best):
    """Exact test of the candidate pairs (point ``pidx``, face ``fidx``); keep each point's nearest."""
    if len(pidx) == 0:
        return
    b = closest_point_triangle(pts[pidx], *(tri[fidx, k] for k in range(3)))
    d = np.linalg.norm(pts[pidx] - np.einsum("mk,mkc->mc", b, tri[fidx]), axis=1)
    order = np.lexsort((d, pidx))  # per point, its nearest candidate first
    first = order[np.r_[True, pidx[order][1:] != pidx[order][:-1]]]
    p = pidx[first]
    better = d[first] < best[2][p]
    p, first = p[better], first[better]
    best[0][p], best[1][p], best[2][p] = fidx[first], b[first], d[first]


def closest_points(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, chunk: int = 8192) -> Correspondence:
    """Exact closest points of ``points`` on the surface (``vertices``, ``faces``).

    First the faces around each point's 4 nearest vertices give a distance ``d1`` that bounds the
    answer from above. A face whose centroid is farther than ``d1 + R_f`` (``R_f`` its largest
    centroid-to-corner distance) cannot hold a closer point; the faces are grouped by ``R_f`` (one
    KD-tree of centroids per group, queried with the group's largest ``R_f``), and every face left
    is tested exactly, so the result is the true closest point.

    Args:
        points: (N2, 3) query points, metres.
        vertices: (N1, 3) mesh vertices; faces: (F, 3) triangles.
        chunk: points processed together (memory).

    Returns:
        :class:`Correspondence`.
    """
    points = np.asarray(points, dtype=np.float64)
    faces_in = np.asarray(faces, dtype=np.int64)
    used, faces = np.unique(faces_in, return_inverse=True)  # only the vertices the faces use
    faces = faces.reshape(-1, 3)
    vertices = np.asarray(vertices, dtype=np.float64)[used]
    tri = vertices[faces]  # (F, 3, 3)
    cen = tri.mean(1)
    rad = np.linalg.norm(tri - cen[:, None], axis=2).max(1)
    # vertex -> incident faces (CSR)
    inc = sp.csr_matrix((np.ones(faces.size), (faces.ravel(), np.repeat(np.arange(len(faces)), 3))),
                        shape=(len(vertices), len(faces)))
    edges = np.unique(np.quantile(rad, [0.0, 0.5, 0.8, 0.95, 0.99, 1.0]))
    groups = [np.flatnonzero((rad >= lo) & ((rad < hi) | (hi == edges[-1])))
              for lo, hi in zip(edges[:-1], edges[1:])] if len(edges) > 1 else [np.arange(len(faces))]
    trees = [(g, cKDTree(cen[g]), float(rad[g].max())) for g in groups if len(g)]
    vtree = cKDTree(vertices)
    n = len(points)
    best = [np.zeros(n, dtype=np.int64), np.zeros((n, 3)), np.full(n, np.inf)]
    for s in range(0, n, chunk):
        pts = points[s : s + chunk]
        m = len(pts)
        part = [np.zeros(m, dtype=np.int64), np.zeros((m, 3)), np.full(m, np.inf)]
        _, near = vtree.query(pts, k=min(4, len(vertices)))
        near = near.reshape(m, -1)
        sel = inc[near.ravel()].tocoo()
        rows = np.repeat(np.arange(m), near.shape[1])[sel.row]
        _best_of(pts, tri, rows, sel.col.astype(np.int64), part)
        for g, tree, rmax in trees:
            cand = tree.query_ball_point(pts, part[2] + rmax + 1e-9)
            counts = np.fromiter((len(c) for c in cand), dtype=np.int64, count=m)
            if counts.sum() == 0:
                continue
            pidx = np.repeat(np.arange(m), counts)
            fidx = g[np.concatenate([np.asarray(c, dtype=np.int64) for c in cand if len(c)])]
            keep = np.linalg.norm(pts[pidx] - cen[fidx], axis=1) - rad[fidx] <= part[2][pidx] + 1e-12
            _best_of(pts, tri, pidx[keep], fidx[keep], part)
        for i in range(3):
            best[i][s : s + m] = part[i]
    face, bary, dist = best
    return Correspondence(face, faces_in[face], bary, dist)


def mapping_matrix(corr: Correspondence, num_source: int) -> sp.csr_matrix:
    """W' of Eq. 3.7: (N2, N1) sparse, row i holds the barycentrics (u_i, v_i, w_i) at (a, b, c)."""
    return sparse_rows(corr.corners, corr.bary, num_source)


def sparse_rows(corners: np.ndarray, bary: np.ndarray, num_source: int) -> sp.csr_matrix:
    """W' from (N2, 3) corner indices and (N2, 3) barycentrics (e.g. a model file's ``reparam_*``)."""
    n2 = len(corners)
    rows = np.repeat(np.arange(n2), 3)
    return sp.csr_matrix((np.asarray(bary, np.float64).ravel(), (rows, np.asarray(corners).ravel())), shape=(n2, num_source))


def block_matrix(corr: Correspondence, num_source: int) -> sp.csr_matrix:
    """W of Sec. 3.3.2: (3 N2, 3 N1) sparse, blocks ``u_i I_3`` at (i, a), ``v_i I_3``, ``w_i I_3``."""
    return sp.kron(mapping_matrix(corr, num_source), sp.identity(3), format="csr")


def apply_rows(wp: sp.spmatrix, values: np.ndarray) -> np.ndarray:
    """``W'`` applied to a per-vertex array: (N1, ...) -> (N2, ...) (Eqs. 3.6, 3.7)."""
    values = np.asarray(values)
    flat = values.reshape(values.shape[0], -1).astype(np.float64)
    return np.asarray(wp @ flat).reshape(wp.shape[0], *values.shape[1:])


def apply_basis(wp: sp.spmatrix, basis: np.ndarray) -> np.ndarray:
    """``W P`` for a stack of per-vertex fields: (K, N1, 3) -> (K, N2, 3) (Eq. 3.6)."""
    k, n1, c = basis.shape
    flat = np.asarray(basis, dtype=np.float64).transpose(1, 0, 2).reshape(n1, k * c)
    return np.asarray(wp @ flat).reshape(wp.shape[0], k, c).transpose(1, 0, 2)


@dataclass
class ShapeSpace:
    """A Gaussian shape space ``N(mean, components^T components)`` in principal axes.

    Attributes:
        mean: (N, 3) mean shape, metres.
        components: (K, N, 3) orthogonal principal components scaled by their standard deviation
            (metres per standard deviation), largest variance first.
        variances: (K,) variance of each component, m^2 (the squared norm of the component).
        coeff_map: (K, K0) ``A`` and ``coeff_offset`` (K,) ``a`` with ``c_2 = A c + a``: the
            coefficients of the same body in this space given the K0 coefficients of the source
            model (None when there is no source).
    """

    mean: np.ndarray
    components: np.ndarray
    variances: np.ndarray
    coeff_map: np.ndarray | None = None
    coeff_offset: np.ndarray | None = None


def shape_space_eq35(
    wp: sp.spmatrix, mean1: np.ndarray, basis1: np.ndarray, mean2: np.ndarray, rank_tol: float = 1e-12
) -> ShapeSpace:
    """Eq. 3.5 in low rank: the principal components of ``W Sigma_1 W^T + d d^T``, ``d = mu_2 - W mu_1``.

    ``Sigma_1 = P_1^T P_1`` with P_1 (K, N1, 3) the model's basis in metres per standard deviation
    (scaled PCA, so its rows are ``U S``). With ``M = [W P_1^T, d]`` (3N2 x (K + 1)), ``Sigma_2 = M M^T``
    and the thin SVD ``M = Q S V^T`` gives the components ``Q S`` and variances ``S^2``; the dense
    3N2 x 3N2 matrix is never formed. A body ``mu_1 + P_1^T c`` of the source maps to
    ``W (mu_1 + P_1^T c) = mu_2 + M [c; -1] = mu_2 + (Q S) V^T [c; -1]``, so its coefficients in
    the new space are ``c_2 = V^T [c; -1]`` exactly (``coeff_map``, ``coeff_offset``).

    Args:
        wp: W' (N2, N1).
        mean1: (N1, 3) mu_1; basis1: (K, N1, 3) P_1; mean2: (N2, 3) mu_2 (the aligned new template).
        rank_tol: components with a singular value below ``rank_tol`` times the largest are dropped.

    Returns:
        :class:`ShapeSpace` with up to K + 1 components.
    """
    k = basis1.shape[0]
    mapped = apply_basis(wp, basis1)  # (K, N2, 3) W P_1
    d = np.asarray(mean2, dtype=np.float64) - apply_rows(wp, mean1)
    m = np.concatenate([mapped.reshape(k, -1), d.reshape(1, -1)]).T  # (3 N2, K + 1)
    q, s, vt = np.linalg.svd(m, full_matrices=False)
    keep = s > rank_tol * max(float(s[0]), 1e-300)
    q, s, vt = q[:, keep], s[keep], vt[keep]
    sign = np.sign(vt[np.arange(len(vt)), np.abs(vt).argmax(1)])  # deterministic signs
    q, vt = q * sign, vt * sign[:, None]
    comps = (q * s).T.reshape(len(s), -1, 3)
    return ShapeSpace(np.asarray(mean2, dtype=np.float64), comps, s**2, vt[:, :k], -vt[:, k])


def shape_space_pca(mean: np.ndarray, basis: np.ndarray) -> ShapeSpace:
    """The principal axes of ``N(mean, P^T P)`` for any basis P (K, N, 3) (thin SVD; K small).

    The coefficient map sends the coefficients of ``basis`` to those of the principal axes.
    """
    k = basis.shape[0]
    m = np.asarray(basis, dtype=np.float64).reshape(k, -1).T  # (3N, K)
    q, s, vt = np.linalg.svd(m, full_matrices=False)
    sign = np.sign(vt[np.arange(len(vt)), np.abs(vt).argmax(1)])
    q, vt = q * sign, vt * sign[:, None]
    return ShapeSpace(np.asarray(mean, dtype=np.float64), (q * s).T.reshape(k, -1, 3), s**2, vt, np.zeros(k))


# ------------------------------------------------------------------------------------------------
# Aligning the new template (Sec. 3.3.2)


def _similarity(src: np.ndarray, dst: np.ndarray, scale: bool) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama: (s, R, t) minimising ``sum ||s R src + t - dst||^2``."""
    ms, md = src.mean(0), dst.mean(0)
    xs, xd = src - ms, dst - md
    u, sig, vt = np.linalg.svd(xd.T @ xs / len(src))
    e = np.eye(3)
    e[2, 2] = np.sign(np.linalg.det(u @ vt))
    rot = u @ e @ vt
    s = float(np.trace(np.diag(sig) @ e) / (xs**2).sum(1).mean()) if scale else 1.0
    return s, rot, md - s * rot @ ms


def align_template(
    vertices: np.ndarray,
    target_vertices: np.ndarray,
    target_faces: np.ndarray,
    mode: str = "auto",
    near: float = 0.005,
    iterations: int = 50,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Rigid (+ scale) ICP of a new template onto the model's template surface (Sec. 3.3.2).

    Args:
        vertices: (N2, 3) new template vertices.
        target_vertices, target_faces: the model's template surface.
        mode: ``none`` (as given), ``rigid``, ``similarity`` (rigid + uniform scale), or ``auto``:
            ``none`` when the mean vertex-to-surface distance as given is below ``near`` (a remesh
            or subdivision of the model's own surface: an ICP would trade its known, smooth offset
            from the old surface for a sub-millimetre shift), else ``rigid``.
        near: metres, the threshold of ``auto``.
        iterations: ICP iterations at most (stops when the mean distance changes < 1e-7 m).

    Returns:
        (aligned (N2, 3), the 4x4 transform applied (s R | t), a report: mode used, mean distance
        in mm before and after, scale; the :class:`Correspondence` of the aligned vertices).
    """
    if mode not in ALIGN_MODES:
        raise ValueError(f"align must be one of {ALIGN_MODES}, got {mode!r}")
    x0 = np.asarray(vertices, dtype=np.float64)
    corr = closest_points(x0, target_vertices, target_faces)
    before = float(corr.distance.mean())
    used = mode
    if mode == "auto":
        used = "none" if before < near else "rigid"
    mat = np.eye(4)
    x = x0
    if used != "none":
        tv = np.asarray(target_vertices, dtype=np.float64)
        s = 1.0
        if used == "similarity":  # a template in other units or size: match the RMS radius first
            s = float(np.sqrt(((tv - tv.mean(0)) ** 2).sum(1).mean() / ((x0 - x0.mean(0)) ** 2).sum(1).mean()))
        rot, t = np.eye(3), tv.mean(0) - s * x0.mean(0)
        prev = np.inf
        for _ in range(iterations):
            x = s * x0 @ rot.T + t
            corr = closest_points(x, target_vertices, target_faces)
            cur = float(corr.distance.mean())
            if abs(prev - cur) < 1e-7:
                break
            prev = cur
            s, rot, t = _similarity(x0, corr.points(tv), used == "similarity")
        x = s * x0 @ rot.T + t
        mat[:3, :3], mat[:3, 3] = s * rot, t
        corr = closest_points(x, target_vertices, target_faces)
    report = {"mode": used, "mean_distance_mm_before": 1000 * before,
              "mean_distance_mm_after": 1000 * float(corr.distance.mean()),
              "scale": float(np.cbrt(np.linalg.det(mat[:3, :3])))}
    return x, mat, report, corr


def mirror_map(vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """Each vertex's mirror across x = 0: the nearest vertex to ``(-x, y, z)``.

    Returns:
        ((N,) indices, the largest distance in metres from a mirrored vertex to its match).
    """
    flipped = np.asarray(vertices, dtype=np.float64) * np.array([-1.0, 1.0, 1.0])
    d, idx = cKDTree(vertices).query(flipped)
    return idx.astype(np.int32), float(d.max())
