"""Tests of blsm/learn/keypoint_fit.py: registration from 3D keypoints (thesis Eqs. 6.4-6.6)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from blsm.learn.keypoint_fit import (
    KeypointFitConfig,
    KeypointSet,
    fit_keypoints,
    fit_shape,
    geman_mcclure,
    load_keypoint_config,
    smoothing,
)

pytestmark = pytest.mark.usefixtures("one_thread")

FAST = dict(rigid_iterations=10, trial_iterations=40, iterations=120)


def _bodies(model, angles_scale: float, frames: int, seed: int = 0, turn: float = 2.5, shape: float = 0.0):
    """A population subject of the packaged model in ``frames`` poses (a slow motion), its output."""
    g = torch.Generator().manual_seed(seed)
    base = torch.randn(1, model.num_dofs, generator=g) * angles_scale
    drift = torch.randn(1, model.num_dofs, generator=g) * 0.15
    t = torch.linspace(0, 1, frames)[:, None]
    x = (base + drift * t).to(model.template.dtype)
    go = torch.zeros(frames, 3, dtype=model.template.dtype)
    go[:, 1] = turn + 0.3 * t[:, 0]
    tr = torch.tensor([[0.2, 0.05, -0.4]], dtype=model.template.dtype) + 0.2 * t
    k = 3
    cs = model.population_shape[k:k + 1] + shape * torch.randn(1, model.num_shape_coeffs, generator=g)
    with torch.no_grad():
        return model(pose=x, bone=model.population_bone[k:k + 1].expand(frames, -1),
                     shape=cs.expand(frames, -1), global_orient=go, transl=tr)


def test_geman_mcclure():
    d2 = torch.tensor([0.0, 1e-6, 0.01, 100.0])
    r = geman_mcclure(d2, 0.05)
    assert r[0] == 0 and r[1] == pytest.approx(1e-6, rel=1e-3)  # quadratic near 0
    assert r[3] < 0.05**2 and r[3] > 0.99 * 0.05**2  # bounded by sigma^2
    assert (r[1:] > r[:-1]).all()


def test_keypoint_set_matches_model(model):
    out = _bodies(model, 0.3, 2)
    kps = KeypointSet.of_model(model)
    again = kps.evaluate(out.vertices[:, kps.vertices], out.joints)
    torch.testing.assert_close(again, out.keypoints)
    sub = KeypointSet.of_model(model, ["nose", "left_knee", "heel_r"])
    assert sub.names == ["nose", "left_knee", "heel_r"] and sub.joint[1] >= 0 and sub.joint[0] < 0
    with pytest.raises(ValueError, match="unknown keypoint names"):
        KeypointSet.of_model(model, ["nose", "tail"])


def test_fit_recovers_pose_and_bones(model):
    """Exact keypoints of a known body (facing away from the rest pose, turn 2.5 rad): the fit
    finds the facing, the pose and the bones to within a few millimetres of keypoint error."""
    out = _bodies(model, 0.4, 1)
    kps = KeypointSet.of_model(model)
    fit = fit_keypoints(model, kps, out.keypoints, config=KeypointFitConfig(**FAST))
    assert float(fit.keypoint_error[0]) < 0.012
    v = fit.vertices(model)
    err = (v - out.vertices).norm(dim=-1).mean()
    assert float(err) < 0.03  # shape coefficients are not fitted here: the rest is soft tissue
    # The bone scales come close to the subject's (population bone coefficients 3).
    b_true = out.bone_scales[0]
    assert float((fit.bone_scales(model)[0] - b_true).abs().mean()) < 0.5 * float((b_true - 1).abs().mean())


def test_robust_to_a_swapped_pair(model):
    out = _bodies(model, 0.3, 1, seed=1, turn=0.3)
    kps = KeypointSet.of_model(model)
    tgt = out.keypoints.clone()
    i, j = kps.names.index("ankle_l"), kps.names.index("ankle_r")
    tgt[0, [i, j]] = tgt[0, [j, i]]  # a left/right confusion of the detector
    fit = fit_keypoints(model, kps, tgt, config=KeypointFitConfig(**FAST))
    kp = fit.vertices(model)  # the body, not the keypoints
    assert float((kp - out.vertices).norm(dim=-1).mean()) < 0.04
    # Non-robust (huge scale): the swapped pair drags the legs.
    plain = fit_keypoints(model, kps, tgt, config=KeypointFitConfig(**FAST, robust_scale=10.0))
    assert float((plain.vertices(model) - out.vertices).norm(dim=-1).mean()) > float((kp - out.vertices).norm(dim=-1).mean())


def test_smoothing_term():
    cfg = KeypointFitConfig()
    j = torch.zeros(5, 2, 3)
    a = torch.zeros(5, 4)
    assert float(smoothing(j, a, torch.zeros(5, dtype=torch.long), cfg)) == 0.0
    j[2, 0, 0] = 0.01  # a spike at frame 2
    s = float(smoothing(j, a, torch.zeros(5, dtype=torch.long), cfg))
    assert s > 0
    # The same spike across a group boundary on every difference counts less.
    assert float(smoothing(j, a, torch.tensor([0, 0, 1, 1, 1]), cfg)) < s
    assert float(smoothing(j[:1], a[:1], torch.zeros(1, dtype=torch.long), cfg)) == 0.0  # T = 1: zero


def test_smoothing_reduces_jitter(model):
    """A noisy 4-frame sequence: Eq. 6.4 with S has smaller acceleration error than without."""
    t_n = 4
    out = _bodies(model, 0.3, t_n, seed=2, turn=0.3)
    kps = KeypointSet.of_model(model)
    rng = np.random.default_rng(0)
    tgt = out.keypoints + torch.as_tensor(rng.normal(0, 0.015, out.keypoints.shape), dtype=out.keypoints.dtype)
    fast = dict(rigid_iterations=10, trial_iterations=0, iterations=60)  # near the rest facing: Kabsch only
    smooth = fit_keypoints(model, kps, tgt, config=KeypointFitConfig(**fast))
    rough = fit_keypoints(model, kps, tgt, config=KeypointFitConfig(**fast, smooth_accel=0.0, smooth_velocity=0.0,
                                                                    smooth_angle_accel=0.0))

    def acc_err(fit):
        v, g = fit.vertices(model), out.vertices
        a = lambda x: x[2:] - 2 * x[1:-1] + x[:-2]  # noqa: E731
        return float((a(v) - a(g)).norm(dim=-1).mean())

    assert acc_err(smooth) < 0.7 * acc_err(rough)
    assert smooth.bone.shape[0] == 1  # one subject


def test_shape_shared_over_frames(model):
    """Eqs. 6.5-6.6 on 3 frames of one subject: one c_s, and the body closer to the scan surface than
    after the keypoints alone."""
    out = _bodies(model, 0.2, 3, seed=3, turn=0.3, shape=2.0)  # a shape the keypoints cannot show
    kps = KeypointSet.of_model(model)
    cfg = KeypointFitConfig(rigid_iterations=10, trial_iterations=0, iterations=100, surface_rounds=4,
                            surface_iterations=15, scan_samples=3000, model_samples=2000)
    fit = fit_keypoints(model, kps, out.keypoints, config=cfg)
    # Moved 3 cm off, and no keypoint term: only the MNN surface term (Eq. 6.6) can bring it back.
    fit = dataclasses.replace(fit, transl=fit.transl + torch.tensor([0.0, 0.0, 0.03]))
    faces = model.faces.numpy()
    scans = [(out.vertices[t].double().numpy(), faces) for t in range(3)]
    shaped = fit_shape(model, kps, out.keypoints, scans, fit, config=dataclasses.replace(cfg, lambda_kp=0.0))
    assert shaped.shape.shape == (1, model.num_shape_coeffs) and float(shaped.shape.abs().sum()) > 0
    from scipy.spatial import cKDTree

    def surface_gap(f):  # mean distance of the model's vertices to the scan (what MNN reduces)
        v = f.vertices(model).double().numpy()
        return np.mean([cKDTree(scans[t][0]).query(v[t])[0].mean() for t in range(3)])

    assert surface_gap(shaped) < 0.5 * surface_gap(fit)
    assert float((shaped.vertices(model) - out.vertices).norm(dim=-1).mean()) < 0.015
    st1 = shaped.stage1(model)
    assert st1.bone_scales.shape == (3, model.num_joints) and torch.equal(st1.bone_scales[0], st1.bone_scales[2])


def test_bad_input(model, tmp_path):
    kps = KeypointSet.of_model(model, ["nose", "left_knee", "right_knee", "pelvis", "neck"])
    with pytest.raises(ValueError, match=r"must be \(T, 5, 3\)"):
        fit_keypoints(model, kps, torch.zeros(2, 4, 3))
    few = torch.full((1, 5, 3), float("nan"))
    few[0, :3] = 0.0
    with pytest.raises(ValueError, match="frame 0 has 3 usable keypoints"):
        fit_keypoints(model, kps, few)
    bad = tmp_path / "k.yaml"
    bad.write_text("robust_scal: 0.1\n")
    with pytest.raises(ValueError, match="k.yaml: robust_scal: unknown key"):
        load_keypoint_config(bad)
    bad.write_text("robust_scale: -1\n")
    with pytest.raises(ValueError, match="k.yaml"):
        load_keypoint_config(bad)


def test_search_hands_fine_grid_around_the_fit(model):
    """The first search picks HAND_GRID's nearest combination; ``around=True`` steps HAND_GRID_FINE from
    the fitted angles and so reaches angles between the coarse values; a fit already right stays."""
    from blsm.learn.end_search import HAND_GRID, HAND_GRID_FINE, search_hands
    from blsm.learn.keypoint_fit import KeypointFit
    from blsm.learn.posing import pose

    dtype = model.template.dtype
    names = [k.format(s="l") for k in HAND_GRID]
    idx = [model.dof_names.index(n) for n in names]
    truth = torch.zeros(1, model.num_dofs, dtype=dtype)
    truth[0, idx] = torch.tensor([0.75, 0.15, 0.3], dtype=dtype)  # between HAND_GRID's values, on the fine steps
    lim = model.dof_limits.to(dtype)
    assert bool(((truth[0, idx] >= lim[idx, 0]) & (truth[0, idx] <= lim[idx, 1])).all())
    go, tr = torch.zeros(1, 3, dtype=dtype), torch.zeros(1, 3, dtype=dtype)
    with torch.no_grad():
        scan = pose(model, model.template[None], angles=truth, global_orient=go, transl=tr).vertices[0].double().numpy()
    scans = [(scan, model.faces.numpy())]
    fit = KeypointFit(torch.zeros(1, dtype=torch.long), torch.zeros(1, model.num_bone_coeffs, dtype=dtype),
                      torch.zeros(1, model.num_shape_coeffs, dtype=dtype), torch.zeros(1, model.num_dofs, dtype=dtype),
                      go, tr, torch.zeros(1, dtype=dtype))
    coarse = search_hands(model, fit, scans)
    got = coarse.angles[0, idx]
    assert all(min(abs(float(a) - v) for v in HAND_GRID[k]) < 1e-6 for a, k in zip(got, HAND_GRID, strict=True))
    # the coarse grid's values only
    err_coarse = float((got - truth[0, idx]).abs().max())
    assert err_coarse > 0.1
    fine = search_hands(model, coarse, scans, around=True)
    err_fine = float((fine.angles[0, idx] - truth[0, idx]).abs().max())
    assert err_fine < 0.05 < err_coarse
    again = search_hands(model, fine, scans, around=True)  # the current angles are a candidate: kept
    torch.testing.assert_close(again.angles, fine.angles)
    steps = [max(abs(v) for v in vals) for vals in HAND_GRID_FINE.values()]
    assert all(s < 0.5 for s in steps) and all(0.0 in vals for vals in HAND_GRID_FINE.values())


def test_search_feet_around_the_fit(model):
    """``search_feet`` moves a foot that the keypoint fit left 0.3 rad off back onto the scan."""
    from blsm.learn.end_search import FOOT_GRID_FINE, search_feet
    from blsm.learn.keypoint_fit import KeypointFit
    from blsm.learn.posing import pose

    dtype = model.template.dtype
    idx = [model.dof_names.index(k.format(s="r")) for k in FOOT_GRID_FINE]
    truth = torch.zeros(1, model.num_dofs, dtype=dtype)
    truth[0, idx] = torch.tensor([0.3, 0.15, -0.15], dtype=dtype)
    go, tr = torch.zeros(1, 3, dtype=dtype), torch.zeros(1, 3, dtype=dtype)
    with torch.no_grad():
        scan = pose(model, model.template[None], angles=truth, global_orient=go, transl=tr).vertices[0].double().numpy()
    fit = KeypointFit(torch.zeros(1, dtype=torch.long), torch.zeros(1, model.num_bone_coeffs, dtype=dtype),
                      torch.zeros(1, model.num_shape_coeffs, dtype=dtype), torch.zeros(1, model.num_dofs, dtype=dtype),
                      go, tr, torch.zeros(1, dtype=dtype))
    out = search_feet(model, fit, [(scan, model.faces.numpy())])
    torch.testing.assert_close(out.angles, truth)  # the right foot found, the left one (already right) kept
