"""Tests of blsm/learn/registration/surface_fit.py: MNN pairs, the energy terms and the free-form refinement
(thesis Eqs. 5.14-5.25)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from synthetic_scans import synthetic_scan

from blsm.learn.posing import pose
from blsm.learn.registration.landmark_fit import fit_landmarks
from blsm.learn.registration.register import scan_data
from blsm.learn.registration.register_config import RegisterConfig
from blsm.learn.registration.surface_fit import (
    Stage2Energy,
    edge_terms,
    mutual_nearest_neighbours,
    pair_term,
    refine,
    sample_surface,
)
from blsm.mesh import mesh_edges

pytestmark = pytest.mark.usefixtures("one_thread")


def test_mnn_is_mutual_against_brute_force(gen):
    rng = np.random.default_rng(0)
    a, b = rng.random((60, 3)), rng.random((45, 3))
    ia, ib = mutual_nearest_neighbours(a, b)
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)
    nab, nba = d.argmin(1), d.argmin(0)
    expect = [(i, nab[i]) for i in range(len(a)) if nba[nab[i]] == i]
    assert list(zip(ia.tolist(), ib.tolist())) == [(int(i), int(j)) for i, j in expect]
    assert 0 < len(expect) < len(b)  # a real subset, so the test can fail both ways
    e1, e2 = mutual_nearest_neighbours(a[:0], b)
    assert len(e1) == len(e2) == 0


def test_edge_terms_zero_at_stage1_mesh(model, gen):
    edges = mesh_edges(model.faces)
    assert edges.shape[0] > model.num_vertices
    s_t = model.template[None] + 0.01 * torch.randn(1, model.num_vertices, 3, generator=gen)
    ev, el = edge_terms(s_t, s_t, edges)
    assert float(ev) == 0.0 and float(el) == 0.0
    ev2, el2 = edge_terms(s_t * 1.1, s_t, edges)
    assert float(ev2) > 0 and float(el2) > 0
    ev3, _ = edge_terms(s_t + torch.tensor([0.1, 0.0, 0.0]), s_t, edges)  # translation keeps edges
    assert float(ev3) < 1e-12


def test_pair_term_point_to_point_and_point_to_plane():
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    r = torch.tensor([[0.003, 0.004, 0.0], [0.0, 0.002, 0.0]], dtype=torch.float64)  # along, across
    assert float(pair_term(r, None)) == pytest.approx((0.005**2 + 0.002**2) / 2)  # Eq. 5.15
    assert float(pair_term(r, n, 0.0)) == pytest.approx(0.002**2 / 2)  # only the normal part
    assert float(pair_term(r, n, 0.5)) == pytest.approx((0.5 * 0.005**2 + 0.002**2) / 2)
    with pytest.raises(ValueError, match="normals"):
        pair_term(r, None, 0.0)
    with pytest.raises(ValueError, match="mnn_tangent_weight"):
        RegisterConfig(mnn_tangent_weight=1.5)


def test_refine_starts_from_init(model, gen, selection):
    """With zero iterations stage 2 returns its initial V_D, and S^ = S^_T + A V_D (Eq. 12)."""
    scan = synthetic_scan(model, gen, posed=True, selection=selection)
    data = scan_data(scan, selection, "scan")
    cfg = RegisterConfig(stage1_iterations=20, stage1_shape_iterations=0, surface_rounds=0, iterations=0)
    st1 = fit_landmarks(model, torch.as_tensor(data.landmarks[None]), selection, cfg)
    st1 = dataclasses.replace(st1, shape_offsets=None)
    init = 0.01 * torch.randn(1, model.num_vertices, 3, generator=gen, dtype=model.template.dtype)
    v_d, s_hat, _ = refine(model, [data], st1, selection, cfg, init=init)
    torch.testing.assert_close(v_d, init)
    with torch.no_grad():
        again = pose(model, model.template + init[0], bone_scales=st1.bone_scales, angles=st1.angles,
                     global_orient=st1.global_orient, transl=st1.transl).vertices
    torch.testing.assert_close(s_hat, again, atol=1e-5, rtol=0)
    energy = Stage2Energy(model, [data], st1, selection, cfg)
    torch.testing.assert_close(energy.displacement(energy.mesh(init)), init, atol=1e-5, rtol=0)
    at_stage1 = energy.terms(energy.s_t, energy.pairs(energy.s_t, np.random.default_rng(0)))
    assert float(at_stage1["ev"]) == 0.0 and float(at_stage1["rigid"]) == 0.0  # S^ = S^_T
    moved = energy.terms(s_hat, energy.pairs(s_hat, np.random.default_rng(0)))
    assert float(moved["ev"]) > 0 and float(energy.total(moved)) > cfg.lambda_ev * float(moved["ev"])
    # "sum" normalisation: the same terms times their element counts, over V
    summed = Stage2Energy(model, [data], st1, selection, dataclasses.replace(cfg, normalisation="sum"))
    pairs = energy.pairs(s_hat, np.random.default_rng(1))
    m, s = energy.terms(s_hat, pairs), summed.terms(s_hat, pairs)
    nv = model.num_vertices
    torch.testing.assert_close(s["mnn"], m["mnn"] * m["pairs"].to(m["mnn"].dtype) / nv)
    torch.testing.assert_close(s["ev"], m["ev"] * energy.edges.shape[0] / nv)
    torch.testing.assert_close(s["lm"], m["lm"] * energy.lm_count / nv)
    torch.testing.assert_close(s["smooth"], m["smooth"])


def test_sample_surface_on_triangle():
    rng = np.random.default_rng(0)
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 0]], float)
    f = np.array([[0, 1, 2], [1, 3, 2]])
    fi, w = sample_surface(v, f, 4000, rng)
    assert np.allclose(w.sum(1), 1) and (w >= 0).all()
    area = np.array([0.5, 0.5 * np.linalg.norm(np.cross(v[3] - v[1], v[2] - v[1]))])
    assert abs((fi == 0).mean() - area[0] / area.sum()) < 0.03
