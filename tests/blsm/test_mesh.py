"""Tests of blsm/mesh.py: edges and the uniform Laplacian (thesis Eqs. 5.17-5.20)."""

from __future__ import annotations

import numpy as np
import torch

from blsm.mesh import mesh_edges, uniform_laplacian, uniform_laplacian_matrix


def _grid(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    ij = torch.stack(torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij"), -1).reshape(-1, 2)
    verts = torch.cat([ij.double() * 0.01, torch.zeros(n * n, 1, dtype=torch.float64)], 1)
    k = torch.arange(n * n).reshape(n, n)
    a, b, c, d = k[:-1, :-1].flatten(), k[1:, :-1].flatten(), k[:-1, 1:].flatten(), k[1:, 1:].flatten()
    faces = torch.cat([torch.stack([a, b, d], 1), torch.stack([a, d, c], 1)])
    return verts, faces


def test_uniform_laplacian_flat_grid():
    verts, faces = _grid(6)
    edges = mesh_edges(faces)
    lap = uniform_laplacian(verts[None], edges)[0].reshape(6, 6, 3)
    assert float(lap[1:-1, 1:-1].abs().max()) < 1e-12  # Eq. 5.17 vanishes inside a regular grid
    assert float(lap[0, 0].norm()) > 1e-3  # but not at a corner
    bumped = verts.clone()
    bumped[14, 2] = 0.01
    lap_b = uniform_laplacian(bumped[None], edges)[0]
    np.testing.assert_allclose(float(lap_b[14, 2]), -0.01, rtol=1e-9)  # all 6 neighbours flat
    # Against the dense matrix form of Eqs. 5.19-5.20.
    n = verts.shape[0]
    adj = torch.zeros(n, n, dtype=torch.float64)
    adj[edges[:, 0], edges[:, 1]] = 1
    adj[edges[:, 1], edges[:, 0]] = 1
    lmat = adj / adj.sum(1, keepdim=True) - torch.eye(n, dtype=torch.float64)
    torch.testing.assert_close(uniform_laplacian(bumped[None], edges)[0], lmat @ bumped)


def test_mesh_edges_are_unique_and_ordered():
    _, faces = _grid(3)
    e = mesh_edges(faces)
    assert (e[:, 0] < e[:, 1]).all() and len(torch.unique(e, dim=0)) == len(e)
    assert len(e) == 16  # 12 grid edges + 4 diagonals


def test_laplacian_matrix_equals_the_edge_form(model):
    v = model.template.double()
    lmat = uniform_laplacian_matrix(model.faces.numpy(), model.num_vertices)
    assert lmat.shape == (model.num_vertices, model.num_vertices) and lmat.dtype == torch.float32
    expect = uniform_laplacian(v[None], mesh_edges(model.faces))[0]
    torch.testing.assert_close(torch.sparse.mm(lmat.double(), v), expect, atol=1e-7, rtol=0)
    # An isolated vertex has a zero Laplacian in both forms.
    lone = uniform_laplacian_matrix(np.array([[0, 1, 2]]), 4)
    out = torch.sparse.mm(lone, torch.ones(4, 3))
    assert float(out.abs().max()) < 1e-6 and lone.to_dense()[3].abs().sum() == 0
