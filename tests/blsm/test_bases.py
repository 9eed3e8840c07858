"""Tests for blsm/learn/training/bases.py: the pure math of learning (bone and shape PCA, Eq. 5.27, Eq. 5.31)."""

from __future__ import annotations

import pytest
import torch

import blsm
from blsm.learn.training.bases import (
    blend_weights,
    bone_mirror_index,
    bone_pca,
    solve_correctives,
    weight_support,
)


def test_bone_pca_two_components():
    gen = torch.Generator().manual_seed(0)
    mirror = bone_mirror_index(blsm.skeleton.BONE_NAMES)
    basis = torch.rand(2, 20, generator=gen, dtype=torch.float64) * 0.02
    basis = 0.5 * (basis + basis[:, mirror])
    mean = 0.1 + torch.rand(20, generator=gen, dtype=torch.float64) * 0.3
    mean = 0.5 * (mean + mean[mirror])
    lengths = mean + torch.randn(50, 2, generator=gen, dtype=torch.float64) @ basis
    pca = bone_pca(lengths, 3, mirror)
    assert float(pca.explained[:2].sum()) > 0.999999
    assert float(pca.explained[0]) < 0.999  # both components matter
    b_mean, p_b = pca.basis(pca.mean_lengths)
    torch.testing.assert_close(b_mean, torch.ones(20, dtype=torch.float64))
    recon = (b_mean + pca.coeffs[:, :2] @ p_b[:2]) * pca.mean_lengths
    torch.testing.assert_close(recon, lengths)
    # Coefficients are in standard deviations.
    torch.testing.assert_close(pca.coeffs[:, :2].std(0), torch.ones(2, dtype=torch.float64))


def test_bone_pca_bad_input():
    with pytest.raises(ValueError, match="N >= 2"):
        bone_pca(torch.ones(1, 20), 2)
    with pytest.raises(ValueError, match="at least 5 bodies"):
        bone_pca(torch.rand(3, 20), 5)


def test_blend_weights_eq_5_31():
    gen = torch.Generator().manual_seed(0)
    raw = torch.randn(30, 5, generator=gen)
    mask = torch.rand(30, 5, generator=gen) > 0.4
    mask[:, 0] = True
    w = blend_weights(raw, mask, 1e-8)
    assert (w >= 0).all() and (w[~mask] == 0).all()
    torch.testing.assert_close(w.sum(1), torch.ones(30))
    # f(x) = f(-x): the sign of W' does not matter.
    torch.testing.assert_close(blend_weights(-raw, mask, 1e-8), w)


def test_weight_support_adds_parent_and_children():
    parents = [-1, 0, 1, 1]
    w = torch.tensor([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    s = weight_support(w, parents)
    assert s.tolist() == [[True, True, True, True], [False, True, False, True]]


def test_solve_correctives_matches_lstsq():
    """The per-vertex normal equations equal a dense least-squares solve of Eq. 5.27."""
    gen = torch.Generator().manual_seed(0)
    n, v, k = 12, 3, 2
    f64 = torch.float64
    lin = torch.randn(n, v, 3, 3, generator=gen, dtype=f64) + 2 * torch.eye(3, dtype=f64)
    off = torch.randn(n, v, 3, generator=gen, dtype=f64)
    coeffs = torch.randn(n, k, generator=gen, dtype=f64)
    tgt = torch.randn(n, v, 3, generator=gen, dtype=f64)
    vbar, pbc = solve_correctives(tgt, coeffs, lin, off, ridge=0.0)
    for i in range(v):  # unknowns [v_i, p_1i, p_2i] (9,)
        rows = torch.cat([torch.cat([lin[m, i] * a for a in torch.cat([torch.ones(1, dtype=f64), coeffs[m]])], 1) for m in range(n)])
        rhs = (tgt[:, i] - off[:, i]).reshape(-1)
        x = torch.linalg.lstsq(rows, rhs[:, None]).solution[:, 0]
        torch.testing.assert_close(vbar[i], x[:3])
        torch.testing.assert_close(pbc[:, i], x[3:].reshape(k, 3))
