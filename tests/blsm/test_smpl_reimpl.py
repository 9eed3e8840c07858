"""Tests of blsm/learn/evaluation/smpl_reimpl.py: the SMPL-type baseline (thesis Sec. 5.5.1)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from blsm.learn.evaluation.fit import FitConfig, staged_fit
from blsm.learn.evaluation.smpl_reimpl import (
    SMPLReimpl,
    SMPLReimplFittable,
    SMPLTrainConfig,
    load_smpl_reimpl,
    regress_joints,
    rest_joints,
    ring_regressor,
    train_smpl_reimpl,
)
from blsm.mocap.prior import load_prior

PRIOR = Path(__file__).resolve().parents[2] / "blsm" / "data" / "pose_prior_cmu.npz"
FIT = FitConfig(iterations=(40, 40, 40, 100), lm_iterations=6)
TRAIN_FIT = FitConfig(iterations=(30, 30, 30, 60), lm_iterations=5)


def _bodies(model, gen, n, pose_scale=0.3):
    """BLSM-made bodies: bone coefficients and the first 3 shape coefficients vary."""
    prior = load_prior(PRIOR)
    x = prior.sample(n, gen).float() * pose_scale
    cb = torch.randn(n, model.num_bone_coeffs, generator=gen)
    cs = torch.zeros(n, model.num_shape_coeffs)
    cs[:, :3] = torch.randn(n, 3, generator=gen)
    with torch.no_grad():
        return model(pose=x, bone=cb, shape=cs).vertices


@pytest.fixture(scope="module")
def trained(model):
    gen = torch.Generator().manual_seed(1)
    train = _bodies(model, gen, 12)
    test = _bodies(model, gen, 2)
    cfg = SMPLTrainConfig(fit=TRAIN_FIT, regressor_steps=200)
    smpl = train_smpl_reimpl(model, train, num_coeffs=11, config=cfg)
    return smpl, test


def test_ring_regressor_rows(model):
    reg, mask = ring_regressor(model)
    assert reg.shape == (model.num_joints, model.num_vertices)
    assert (reg >= 0).all() and torch.allclose(reg.sum(1), torch.ones(model.num_joints))
    assert (reg[~mask] == 0).all()
    # the ring mean lies near its joint (within 6 cm: joints are inside the body; the learnt
    # model's rebased spine joints sit up to 5.3 cm from their ring's mean)
    err = (reg @ model.template - model.heads).norm(dim=1)
    assert float(err.max()) < 0.06


def test_rest_joints_match_blsm(model, gen):
    cb = torch.randn(3, model.num_bone_coeffs, generator=gen)
    out = model(bone=cb)
    assert torch.allclose(rest_joints(model, out.bone_scales), out.rest_joints, atol=1e-6)


def test_trained_regressor_is_sparse_nonnegative_stochastic(trained, model):
    smpl, _ = trained
    r = smpl.joint_regressor
    assert (r >= 0).all()
    assert torch.allclose(r.sum(1), torch.ones(model.num_joints), atol=1e-5)
    assert float((r > 0).float().sum(1).max()) < 0.05 * model.num_vertices  # sparse rows
    meta = smpl.meta["joint_regressor_error_mm"]
    assert meta["trained"] < meta["ring_init"]


def test_rest_pose_is_template(trained):
    smpl, _ = trained
    out = smpl(shape=torch.zeros(1, smpl.num_coeffs))
    assert torch.allclose(out.vertices[0], smpl.template, atol=1e-6)
    joints = regress_joints(smpl.joint_regressor, smpl.template[None])[0]
    assert torch.allclose(out.joints[0], joints, atol=1e-6)


def test_reproduces_held_out_bodies(trained, model):
    smpl, test = trained
    fit = SMPLReimplFittable(smpl)
    full = staged_fit(fit, test, config=FIT)
    mean_only = staged_fit(fit, test, num_coeffs=0, config=FIT)
    full_mm = float(full.mean_error.mean()) * 1000
    assert full_mm < 6.0, full_mm
    assert full_mm < 0.5 * float(mean_only.mean_error.mean()) * 1000


def test_save_load_round_trip(trained, tmp_path, gen):
    smpl, _ = trained
    path = smpl.save(tmp_path / "smpl.npz")
    back = load_smpl_reimpl(path, smpl.skeleton)
    shape = torch.randn(2, smpl.num_coeffs, generator=gen)
    angles = torch.zeros(2, 47)
    angles[:, smpl.skeleton.dof_names.index("knee_l.flex")] = 1.0
    a = smpl(shape=shape, angles=angles).vertices
    b = back(shape=shape, angles=angles).vertices
    assert torch.allclose(a, b, atol=1e-6)
    assert back.meta["num_coeffs"] == smpl.num_coeffs


def test_bad_inputs(trained, tmp_path, model):
    smpl, _ = trained
    with pytest.raises(ValueError, match="shape must be"):
        smpl(shape=torch.zeros(1, smpl.num_coeffs + 1))
    with pytest.raises(ValueError, match="pose must be"):
        smpl(pose=torch.zeros(1, 5))
    bad = tmp_path / "bad.npz"
    np.savez(bad, format=np.array("something-else"))
    with pytest.raises(ValueError, match="bad.npz"):
        load_smpl_reimpl(bad, model)
    with pytest.raises(ValueError, match="missing.npz"):
        load_smpl_reimpl(tmp_path / "missing.npz", model)
    with pytest.raises(ValueError, match="registrations must be"):
        train_smpl_reimpl(model, torch.zeros(3, 10, 3), 2)
    with pytest.raises(ValueError, match="subjects"):
        train_smpl_reimpl(model, model.template.expand(3, -1, -1), 2, subjects=["a"])
    with pytest.raises(ValueError, match="template must be"):
        SMPLReimpl(model, torch.zeros(5, 3), smpl.shape_basis, smpl.joint_regressor)
