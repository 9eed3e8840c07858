"""Small triangle-mesh helpers shared by the model builder, the scan tools, the registration and the
generator: vertex normals and barycentric coordinates (numpy), edges and the uniform Laplacian
(torch)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch


def barycentric(tri: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(N, 3) barycentric coordinates of points ``p`` (N, 3) in the planes of triangles ``tri``
    (N, 3, 3), by Cramer's rule on the triangle's plane; negative outside the triangle."""
    e1, e2, d = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], p - tri[:, 0]
    d00, d01, d11 = (e1 * e1).sum(1), (e1 * e2).sum(1), (e2 * e2).sum(1)
    d20, d21 = (d * e1).sum(1), (d * e2).sum(1)
    den = np.maximum(d00 * d11 - d01 * d01, 1e-30)
    b1 = (d11 * d20 - d01 * d21) / den
    b2 = (d00 * d21 - d01 * d20) / den
    return np.stack([1.0 - b1 - b2, b1, b2], 1)


def face_incidence(faces: np.ndarray, num_vertices: int) -> Any:
    """(V, F) sparse vertex-face incidence (``scipy.sparse`` CSR, float32): one product sums a
    per-face quantity onto the vertices. Build it once per topology for :func:`vertex_normals`."""
    import scipy.sparse as sp

    faces = np.asarray(faces, dtype=np.int64)
    nf = len(faces)
    return sp.csr_matrix(
        (np.ones(3 * nf, np.float32), (faces.reshape(-1), np.repeat(np.arange(nf), 3))), shape=(num_vertices, nf)
    )


def vertex_normals(vertices: np.ndarray, faces: np.ndarray, incidence: Any = None) -> np.ndarray:
    """(V, 3) area-weighted unit vertex normals (in the vertices' dtype) of a mesh (V, 3), (F, 3).

    ``incidence``: the mesh's :func:`face_incidence`, for meshes posed again and again (about 3x
    faster than the default ``np.add.at`` accumulation).
    """
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    if incidence is not None:
        vn = incidence @ fn
    else:
        vn = np.zeros_like(vertices)
        for k in range(3):
            np.add.at(vn, faces[:, k], fn)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return (vn / np.maximum(norm, 1e-12)).astype(vertices.dtype, copy=False)


def mesh_edges(faces: torch.Tensor) -> torch.Tensor:
    """Unique undirected edges (E, 2), ``i < j``, sorted, of a triangle mesh's faces (F, 3)."""
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).long()
    e = torch.sort(e, dim=1).values
    return torch.unique(e, dim=0)


def uniform_laplacian(vertices: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Uniform Laplacian vectors ``delta_i = mean_{j in N(i)} v_j - v_i`` (thesis Eqs. 5.17-5.20).

    Args:
        vertices: (B, V, 3). edges: (E, 2) undirected edges (:func:`mesh_edges`).

    Returns:
        (B, V, 3) Laplacian vectors (0 for isolated vertices); differentiable in ``vertices``.
    """
    n = vertices.shape[1]
    i, j = edges[:, 0], edges[:, 1]
    deg = torch.bincount(torch.cat([i, j]), minlength=n).to(vertices.dtype)
    acc = torch.zeros_like(vertices)
    acc = acc.index_add(1, i, vertices[:, j]).index_add(1, j, vertices[:, i])
    mean = acc / deg.clamp(min=1)[None, :, None]
    return torch.where(deg[None, :, None] > 0, mean - vertices, torch.zeros_like(vertices))


def uniform_laplacian_matrix(faces: Any, num_vertices: int) -> torch.Tensor:
    """The operator of :func:`uniform_laplacian` as a (V, V) sparse float32 matrix ``L``.

    ``(L v)_i = mean_{j in N(i)} v_j - v_i`` for a mesh's (V, 3) vertices ``v``, 0 for isolated
    vertices; build it once per topology when many meshes are measured (e.g. roughness as the mean
    ``|L v|``).

    Args:
        faces: (F, 3) triangle indices (numpy or torch). num_vertices: V.

    Returns:
        (V, V) coalesced sparse COO tensor.
    """
    e = mesh_edges(torch.as_tensor(np.asarray(faces), dtype=torch.long))
    i, j = torch.cat([e[:, 0], e[:, 1]]), torch.cat([e[:, 1], e[:, 0]])
    deg = torch.bincount(i, minlength=num_vertices).float()
    diag = torch.arange(num_vertices)
    idx = torch.stack([torch.cat([i, diag]), torch.cat([j, diag])])
    val = torch.cat([1.0 / deg[i], -(deg > 0).float()])
    return torch.sparse_coo_tensor(idx, val, (num_vertices, num_vertices), check_invariants=True).coalesce()
