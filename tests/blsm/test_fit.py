"""Tests of blsm/learn/evaluation/fit.py: staged fitting (thesis Sec. 5.5.2)."""

from __future__ import annotations

import pytest
import torch

from blsm.learn.evaluation.fit import BLSMFittable, FitConfig, Fittable, initial_params, kabsch, staged_fit
from blsm.mocap.prior import load_prior

PRIOR = "blsm/data/pose_prior_cmu.npz"


def _bodies(model, gen, batch, pose_scale=0.5):
    """BLSM-made registrations: prior poses (scaled towards rest), random coefficients."""
    from pathlib import Path

    prior = load_prior(Path(__file__).resolve().parents[2] / PRIOR)
    x = prior.sample(batch, gen).float() * pose_scale
    cb = torch.randn(batch, model.num_bone_coeffs, generator=gen)
    cs = 0.5 * torch.randn(batch, model.num_shape_coeffs, generator=gen)
    go = 0.1 * torch.randn(batch, 3, generator=gen)
    tr = 0.3 * torch.randn(batch, 3, generator=gen)
    with torch.no_grad():
        out = model(pose=x, bone=cb, shape=cs, global_orient=go, transl=tr)
    return out.vertices, dict(pose=x, bone=cb, shape=cs, global_orient=go, transl=tr, angles=out.angles)


def test_free_coeffs_counts_bone_then_shape(model):
    f = BLSMFittable(model)
    kb, ks = model.num_bone_coeffs, model.num_shape_coeffs
    assert f.free_coeffs(3) == {"bone": 3, "shape": 0}
    assert f.free_coeffs(kb + 2) == {"bone": kb, "shape": 2}
    assert f.num_coeffs_max == kb + ks
    with pytest.raises(ValueError, match="num_coeffs"):
        f.free_coeffs(kb + ks + 1)


def test_stages_partition_vertices_and_atoms(model):
    f = BLSMFittable(model)
    vs, ds = f.vertex_stage(), f.dof_stage()
    assert set(vs.tolist()) == {1, 2, 3, 4} and set(ds.tolist()) == {1, 2, 3, 4}
    names = model.dof_names
    assert all(ds[i] == 1 for i, n in enumerate(names) if n.startswith(("spine", "clavicle")))
    assert all(ds[i] == 2 for i, n in enumerate(names) if n.startswith(("shoulder", "elbow", "wrist")))
    assert all(ds[i] == 3 for i, n in enumerate(names) if n.startswith(("hip", "knee", "ankle")))
    assert all(ds[i] == 4 for i, n in enumerate(names) if n.startswith(("neck", "head")))
    torso = [model.bone_names.index(b) for b in ("pelvis", "spine_01", "spine_02", "spine_03")]
    assert (vs[torch.isin(model.vertex_bones, torch.tensor(torso))] == 1).all()


def test_kabsch_recovers_rotation(gen):
    src = torch.randn(2, 50, 3, generator=gen, dtype=torch.float64)
    from kornia.geometry.conversions import axis_angle_to_rotation_matrix

    r = axis_angle_to_rotation_matrix(torch.randn(2, 3, generator=gen, dtype=torch.float64))
    t = torch.randn(2, 3, generator=gen, dtype=torch.float64)
    r2, t2 = kabsch(src, (r @ src.transpose(1, 2)).transpose(1, 2) + t[:, None])
    assert torch.allclose(r2, r, atol=1e-9) and torch.allclose(t2, t, atol=1e-9)


def test_stage_one_touches_only_torso_parameters(model, gen):
    f = BLSMFittable(model)
    target, _ = _bodies(model, gen, 2)
    init = initial_params(f, target)
    res = staged_fit(f, target, num_coeffs=4, config=FitConfig(iterations=(30, 0, 0, 0)), stages=(1,))
    moved = (res.params["pose"] - init["pose"]).abs().amax(0) > 0
    ds = f.dof_stage()
    assert moved[ds == 1].any()
    assert not moved[ds > 1].any(), [model.dof_names[i] for i in torch.nonzero(moved & (ds > 1)).flatten()]
    # only the first 4 coefficients (all bone ones) are free; the rest stay 0
    assert res.params["bone"][:, :4].abs().sum() > 0
    assert (res.params["bone"][:, 4:] == 0).all() and (res.params["shape"] == 0).all()
    assert (res.params["global_orient"] != init["global_orient"]).any()
    # stage 1's loss only sees torso vertices: moving a leg vertex of the target changes nothing
    target2 = target.clone()
    legs = f.vertex_stage() == 3
    target2[:, legs] += 0.5
    res2 = staged_fit(f, target2, num_coeffs=4, config=FitConfig(iterations=(30, 0, 0, 0)), stages=(1,))
    assert torch.allclose(res2.params["pose"], res.params["pose"], atol=1e-5)


def test_staged_fit_recovers_blsm_registration(model, gen):
    f = BLSMFittable(model)
    target, truth = _bodies(model, gen, 2)
    res = staged_fit(f, target, config=FitConfig(iterations=(60, 60, 60, 150), lm_iterations=6))
    assert res.vertices.shape == target.shape and res.errors.shape == target.shape[:2]
    assert float(res.mean_error.max()) < 1e-3  # < 1 mm mean absolute vertex error
    assert float(res.errors.max()) < 5e-3
    assert torch.allclose(res.params["angles"], truth["angles"], atol=0.05)


def test_pose_only_fit_keeps_fixed_shape(model, gen):
    f = BLSMFittable(model)
    target, truth = _bodies(model, gen, 2)
    fixed = {"bone": truth["bone"], "shape": truth["shape"]}
    cfg = FitConfig(iterations=(60, 60, 60, 150), lm_iterations=15)
    res = staged_fit(f, target, config=cfg, fixed_coeffs=fixed)
    assert torch.equal(res.params["bone"], truth["bone"]) and torch.equal(res.params["shape"], truth["shape"])
    assert float(res.mean_error.max()) < 1e-3
    wrong = {"bone": torch.zeros_like(truth["bone"]), "shape": torch.zeros_like(truth["shape"])}
    res_wrong = staged_fit(f, target, config=cfg, fixed_coeffs=wrong)
    assert float(res_wrong.mean_error.mean()) > 3 * float(res.mean_error.mean())


def test_bad_inputs(model):
    f = BLSMFittable(model)
    with pytest.raises(ValueError, match="targets must be"):
        staged_fit(f, torch.zeros(5, 3))
    with pytest.raises(ValueError, match="vertices"):
        staged_fit(f, torch.zeros(1, 10, 3))
    bad = model.template[None].clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        staged_fit(f, bad)
    with pytest.raises(ValueError, match="stages"):
        staged_fit(f, model.template[None], stages=(5,))
    with pytest.raises(ValueError, match="unknown coefficient group"):
        staged_fit(f, model.template[None], fixed_coeffs={"betas": torch.zeros(1, 3)})
    with pytest.raises(ValueError, match="iterations"):
        FitConfig(iterations=(1, 2, 3))
    with pytest.raises(TypeError, match="abstract"):  # a model must say how it makes vertices
        Fittable()
