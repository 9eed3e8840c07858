"""Mesh down- and up-sampling for the spiral networks (thesis Sec. 4.3.2; CoMA, Ranjan et al. 2018).

Down-sampling is quadric edge collapse (``fast-simplification``, Garland-Heckbert) of a template
*posed in a reference pose* (Fig. 4.2): the collapse history gives the original vertices that
survive, and those keep their **original positions and indices** — ``Q^d`` selects them
(``Q^d_ij = 1`` when fine vertex i is coarse vertex j). Up-sampling ``Q^u`` copies a kept vertex
(weight 1) and places every discarded vertex on its closest triangle of the coarse mesh with the
barycentric coordinates of the closest point (``Q^u`` row weights sum to 1). Both are stored as
gathers, not dense matrices: ``down`` (m,) indices, ``up_index`` (n, 3) and ``up_weight`` (n, 3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Level:
    """One down-sampling step from a fine mesh (n vertices) to a coarse one (m vertices).

    Attributes:
        down: (m,) fine-vertex index of every coarse vertex (``Q^d`` as a gather).
        up_index: (n, 3) coarse vertices each fine vertex is interpolated from.
        up_weight: (n, 3) barycentric weights (rows sum to 1; a kept vertex is ``(1, 0, 0)``).
        faces: (Fc, 3) triangles of the coarse mesh, indexing coarse vertices.
    """

    down: np.ndarray
    up_index: np.ndarray
    up_weight: np.ndarray
    faces: np.ndarray

    def down_matrix(self) -> np.ndarray:
        """Dense ``Q^d`` (n, m) of the thesis (for tests and inspection)."""
        n = len(self.up_index)
        q = np.zeros((n, len(self.down)))
        q[self.down, np.arange(len(self.down))] = 1.0
        return q

    def up_matrix(self) -> np.ndarray:
        """Dense ``Q^u`` (m, n): ``X_fine = Q^u^T X_coarse``."""
        q = np.zeros((len(self.down), len(self.up_index)))
        for k in range(3):
            np.add.at(q, (self.up_index[:, k], np.arange(len(self.up_index))), self.up_weight[:, k])
        return q


def decimate(positions: np.ndarray, faces: np.ndarray, factor: float) -> tuple[np.ndarray, np.ndarray]:
    """Quadric edge collapse to about ``1 / factor`` of the vertices; the survivors keep their place.

    Args:
        positions: (n, 3) vertex positions (the reference pose). faces: (F, 3).
        factor: the vertex reduction (4 keeps about a quarter).

    Returns:
        ``down`` (m,) the surviving fine-vertex indices (ascending) and the coarse faces (Fc, 3)
        indexing positions in ``down``.
    """
    import fast_simplification

    positions = np.asarray(positions, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    n = len(positions)
    target = int(round(len(faces) / factor))
    _, _, collapses = fast_simplification.simplify(positions, faces.astype(np.int32), target_count=target,
                                                   return_collapses=True)
    dec_points, dec_faces, mapping = fast_simplification.replay_simplification(positions, faces.astype(np.int32), collapses)
    collapsed = np.zeros(n, dtype=bool)
    collapsed[np.asarray(collapses, dtype=np.int64)[:, 1]] = True
    used = np.zeros(n, dtype=bool)
    used[faces.ravel()] = True
    mapping = np.asarray(mapping, dtype=np.int64)
    m = len(dec_points)
    # Each coarse vertex is a survivor of the collapses. A survivor left without a triangle is merged
    # by fast-simplification into a nearby coarse vertex, so a coarse vertex may have two surviving
    # candidates: it is the one the collapses moved least (nearest to the coarse point).
    down = np.full(m, -1, dtype=np.int64)
    best = np.full(m, np.inf)
    for v in np.flatnonzero(used & ~collapsed):
        j = mapping[v]
        d = float(np.linalg.norm(positions[v] - dec_points[j]))
        if d < best[j]:
            down[j], best[j] = v, d
    if (down < 0).any():
        raise RuntimeError(f"edge collapse left {(down < 0).sum()} coarse vertices without a surviving original vertex")
    order = np.argsort(down)  # coarse vertices in the fine mesh's order
    rank = np.empty(m, dtype=np.int64)
    rank[order] = np.arange(m)
    coarse_faces = rank[np.asarray(dec_faces, dtype=np.int64).reshape(-1, 3)]
    coarse_faces = coarse_faces[(coarse_faces[:, 0] != coarse_faces[:, 1]) & (coarse_faces[:, 1] != coarse_faces[:, 2])
                                & (coarse_faces[:, 0] != coarse_faces[:, 2])]
    return down[order], coarse_faces


def upsampling(positions: np.ndarray, down: np.ndarray, coarse_faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Q^u`` of Sec. 4.3.2 as a gather: kept vertices copy themselves, discarded ones take the
    barycentric coordinates of their closest point on the coarse mesh.

    Args:
        positions: (n, 3) fine positions (the reference pose). down: (m,) kept fine indices.
        coarse_faces: (Fc, 3) coarse triangles (indices into ``down``).

    Returns:
        ``up_index`` (n, 3) and ``up_weight`` (n, 3).
    """
    import trimesh

    positions = np.asarray(positions, dtype=np.float64)
    n, m = len(positions), len(down)
    coarse = trimesh.Trimesh(positions[down], coarse_faces, process=False)
    idx = np.zeros((n, 3), dtype=np.int64)
    w = np.zeros((n, 3), dtype=np.float64)
    kept = np.full(n, -1, dtype=np.int64)
    kept[down] = np.arange(m)
    idx[down, 0] = np.arange(m)
    w[down, 0] = 1.0
    rest = np.flatnonzero(kept < 0)
    if len(rest):
        closest, _, tri = trimesh.proximity.closest_point(coarse, positions[rest])
        corners = coarse_faces[tri]  # (r, 3)
        bary = trimesh.triangles.points_to_barycentric(coarse.vertices[corners], closest)
        bary = np.clip(bary, 0.0, None)
        bary /= bary.sum(1, keepdims=True)
        idx[rest], w[rest] = corners, bary
    return idx, w


def build_levels(positions: np.ndarray, faces: np.ndarray, factors: tuple[float, ...]) -> list[Level]:
    """Successive :class:`Level`s with the given vertex reduction factors (thesis: 4, 2, 2, 2)."""
    levels = []
    pos, fcs = np.asarray(positions, dtype=np.float64), np.asarray(faces, dtype=np.int64)
    for f in factors:
        down, cf = decimate(pos, fcs, f)
        ui, uw = upsampling(pos, down, cf)
        levels.append(Level(down=down, up_index=ui, up_weight=uw, faces=cf))
        pos, fcs = pos[down], cf
    return levels
