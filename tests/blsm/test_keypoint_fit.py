"""Tests of blsm/learn/registration/keypoint_fit.py: registration from 3D keypoints (thesis Eqs. 6.4-6.6)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from blsm.learn.registration.keypoint_fit import (
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


def _quadratic_motion(times: torch.Tensor):
    """Joints (T, 2, 3) and angles (T, 4) of a motion of constant acceleration (3 m/s^2, 20 rad/s^2)."""
    t = times.double()[:, None]
    j = torch.stack([0.1 + 0.5 * t + 0.5 * 3.0 * t**2, 0.9 - 0.5 * 1.0 * t**2, 0.2 * t], -1)  # (T, 1, 3)
    j = torch.cat([j, j + 0.3], 1)  # (T, 2, 3)
    a = (0.5 * 20.0 * t**2).expand(-1, 4)  # (T, 4)
    return j, a


def test_smoothing_follows_frame_spacing():
    """Issue 53: S weighs physical accelerations, so the same motion costs the same per frame triple
    whether its frames are consecutive at 30 fps or 4 clip frames apart (7.5 fps), instead of 4^4 =
    256 times more; at the reference 15 fps (and with no times) it is the per-frame second difference
    weighted 0.1 (1e-4 for the angles), the term the defaults were set with."""
    cfg = KeypointFitConfig()
    g = torch.zeros(3, dtype=torch.long)
    dense = torch.tensor([0.0, 1.0, 2.0]) / 30.0
    sparse = torch.tensor([0.0, 4.0, 8.0]) / 30.0
    s_dense = float(smoothing(*_quadratic_motion(dense), g, cfg, dense))
    s_sparse = float(smoothing(*_quadratic_motion(sparse), g, cfg, sparse))
    assert s_dense > 0
    assert s_sparse == pytest.approx(s_dense, rel=1e-9)
    # The value: weights times the mean squared physical accelerations.
    expected = cfg.smooth_accel * (3.0**2 + 1.0**2) + cfg.smooth_angle_accel * 20.0**2  # (3, -1, 0) m/s^2
    assert s_dense == pytest.approx(expected, rel=1e-9)
    # Unequal spacing (frames 0, 1 and 5 of a 30 fps clip) of the same motion: the same cost.
    uneven = torch.tensor([0.0, 1.0, 5.0]) / 30.0
    assert float(smoothing(*_quadratic_motion(uneven), g, cfg, uneven)) == pytest.approx(s_dense, rel=1e-9)
    # At 15 fps, and without times, the term the weights were set with (0.1 per squared metre of second
    # difference of consecutive frames).
    ref = torch.arange(3, dtype=torch.float64) / 15.0
    j, a = _quadratic_motion(ref)
    d2j = (j[2] - 2 * j[1] + j[0]).square().sum(-1).mean()
    d2a = (a[2] - 2 * a[1] + a[0]).square().mean()
    old = 0.1 * float(d2j) + 1e-4 * float(d2a)
    assert float(smoothing(j, a, g, cfg, ref)) == pytest.approx(old, rel=1e-9)
    assert float(smoothing(j, a, g, cfg)) == pytest.approx(old, rel=1e-9)
    # Velocities by the spacing too: 4 times the spacing, the same displacement per frame: 1/16 the cost.
    vcfg = dataclasses.replace(cfg, smooth_accel=0.0, smooth_angle_accel=0.0, smooth_velocity=1.0)
    j = torch.zeros(2, 1, 3)
    j[1, 0, 0] = 0.1
    v1 = float(smoothing(j, torch.zeros(2, 1), g[:2], vcfg, dense[:2]))
    assert v1 == pytest.approx(3.0**2)  # 0.1 m in 1/30 s: 3 m/s
    assert float(smoothing(j, torch.zeros(2, 1), g[:2], vcfg, sparse[:2])) == pytest.approx(v1 / 16)
    with pytest.raises(ValueError, match="increase"):
        smoothing(j, torch.zeros(2, 1), g[:2], vcfg, torch.tensor([0.1, 0.1]))


def test_frame_times():
    """Times of a sequence's frames: the fps setting, else the scans' meta (time; frame index and fps),
    else unknown (None: the reference 15 fps)."""
    from blsm.learn.registration.keypoint_fit import frame_times

    metas = [{"id": f"frame_{k:04d}", "pose": k, "fps": 7.5} for k in range(3)]  # make_sequence's meta
    t, src = frame_times(metas)
    np.testing.assert_allclose(t.numpy(), [0.0, 4 / 30, 8 / 30])
    assert "fps 7.5" in src
    t, _ = frame_times([{"pose": k, "fps": 30.0} for k in (0, 4, 8)])  # every 4th file of a 30 fps sequence
    np.testing.assert_allclose(t.numpy(), [0.0, 4 / 30, 8 / 30])
    t, _ = frame_times([{"time": 1.0}, {"time": 1.5}, {"time": 2.5}])
    np.testing.assert_allclose(t.numpy(), [1.0, 1.5, 2.5])
    t, src = frame_times(metas, fps=10.0)  # the setting wins
    np.testing.assert_allclose(t.numpy(), [0.0, 0.1, 0.2])
    assert frame_times([{"pose": 0, "fps": 7.5}, {"id": "x"}, None])[0] is None  # not every scan: unknown
    assert frame_times([{"pose": 0, "fps": 7.5}, {"pose": 1, "fps": 15.0}])[0] is None  # two rates
    assert frame_times([{"pose": 0}, {"pose": 1}])[0] is None  # population scans: a pose index, no fps


def test_outlier_frames():
    """A frame is reported when its keypoint error is over twice its sequence's median and over 10 mm."""
    from blsm.learn.registration.keypoint_fit import outlier_frames

    zero3 = torch.zeros(3, dtype=torch.long)
    assert outlier_frames(torch.tensor([0.0062, 0.035, 0.0124]), zero3) == [1]  # issue 53's frames
    assert outlier_frames(torch.tensor([0.001, 0.005, 0.001]), zero3) == []  # far above, but 5 mm
    assert outlier_frames(torch.tensor([0.0065, 0.0139, 0.0068]), zero3) == [1]  # the reproduction's, before
    assert outlier_frames(torch.tensor([0.02, 0.035, 0.025]), zero3) == []  # not twice the median
    assert outlier_frames(torch.tensor([0.005, 0.05]), zero3[:2]) == []  # two frames: no median to beat
    # Per group (sequence): frame 4 is far above its own group's, frame 1 is not above group 0's.
    err = torch.tensor([0.030, 0.040, 0.035, 0.005, 0.050, 0.006, 0.005])
    assert outlier_frames(err, torch.tensor([0, 0, 0, 1, 1, 1, 1])) == [4]


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
    from blsm.learn.posing import pose
    from blsm.learn.registration.end_search import HAND_GRID, HAND_GRID_FINE, search_hands
    from blsm.learn.registration.keypoint_fit import KeypointFit

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
    from blsm.learn.posing import pose
    from blsm.learn.registration.end_search import FOOT_GRID_FINE, search_feet
    from blsm.learn.registration.keypoint_fit import KeypointFit

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
