"""blsm.mocap.plausible: backward feet and limbs through the torso, on hand-made poses."""

from __future__ import annotations

import copy
import itertools

import numpy as np
import pytest
import torch

import blsm
from blsm.joint_limits import unconstrained_from_angles
from blsm.mocap.plausible import PoseChecker


@pytest.fixture(scope="module")
def model():
    return blsm.load()


@pytest.fixture(scope="module")
def checker(model):
    return PoseChecker(model)


def _pose(model, **angles: float) -> torch.Tensor:
    """Unconstrained x of a pose whose named atoms (``hip_l__rotate``) have these angles, others 0;
    an angle of "lo"/"hi" is just inside that limit."""
    names = list(model.dof_names)
    lim = model.dof_limits.double()
    a = torch.zeros(1, len(names), dtype=torch.float64)
    for key, v in angles.items():
        i = names.index(key.replace("__", "."))
        span = float(lim[i, 1] - lim[i, 0])
        a[0, i] = {"lo": float(lim[i, 0]) + 1e-3 * span, "hi": float(lim[i, 1]) - 1e-3 * span}.get(v, v)
    return unconstrained_from_angles(a, lim).float()


def test_rest_pose_is_plausible_with_both_feet_forward(model, checker):
    r = checker.check(_pose(model))
    assert r.plausible.tolist() == [True]
    # At rest the body faces +Z, so the heel-to-toe component along the forward axis is the foot's
    # own z extent, the same for both feet.
    kp = model(angles=torch.zeros(1, model.num_dofs)).keypoints[0].detach().numpy()
    k = list(model.keypoint_names)
    want = kp[k.index("toe_tip_l"), 2] - kp[k.index("heel_l"), 2]
    np.testing.assert_allclose(r.foot_forward[0], [want, want], atol=1e-4)
    assert want > 0.1


def test_the_packaged_limits_cannot_twist_a_straight_leg_backwards(model, checker):
    # Every corner of the twist atoms (hip rotation and abduction, ankle abduction and inversion)
    # leaves the straightened foot pointing forwards: the joint limits stop short of 90 degrees.
    corners = [
        _pose(model, hip_l__rotate=a, hip_l__abduct=b, ankle_l__abduct=c, ankle_l__invert=d)
        for a, b, c, d in itertools.product(("lo", "hi"), ("lo", 0.0, "hi"), ("lo", "hi"), ("lo", 0.0, "hi"))
    ]
    r = checker.check(torch.cat(corners))
    assert not r.foot_backwards.any()
    assert r.foot_forward.min() > 0.02


def test_a_leg_twisted_past_90_degrees_turns_the_foot_backwards(model):
    # A model whose hip may rotate 2.5 rad (not the packaged one): the checker flags the twisted foot.
    wide = copy.deepcopy(model)
    for name in ("hip_l.rotate", "hip_r.rotate"):
        wide.dof_limits[list(model.dof_names).index(name)] = torch.tensor([-2.5, 2.5])
    checker = PoseChecker(wide)
    twisted = _pose(wide, hip_l__rotate=-2.0)
    r = checker.check(twisted)
    assert r.foot_backwards.tolist() == [[True, False]] and r.plausible.tolist() == [False]
    assert r.foot_forward[0, 0] < -0.05
    # The mirrored pose twists the right foot instead, by the same amount.
    r2 = checker.check(wide.mirror_pose(twisted))
    assert r2.foot_backwards.tolist() == [[False, True]]
    np.testing.assert_allclose(r2.foot_forward[0, ::-1], r.foot_forward[0], atol=1e-4)


def test_a_heel_kicked_back_is_not_a_backward_foot(model, checker):
    # Running: thigh back, knee fully flexed, ankle pointed. The toes are behind the heel as posed,
    # but the leg is not twisted, so the test (legs straightened) passes it.
    kick = _pose(model, hip_l__flex="lo", knee_l__flex="hi", ankle_l__plantarflex="hi")
    kp = model(pose=kick).keypoints[0].detach().numpy()
    k = list(model.keypoint_names)
    assert kp[k.index("toe_tip_l"), 2] - kp[k.index("heel_l"), 2] < 0  # toes behind the heel as posed
    r = checker.check(kick)
    assert r.toes_behind_heel.tolist() == [[True, False]]
    assert r.plausible.tolist() == [True]


def test_an_arm_pushed_into_the_chest_is_a_limb_through_the_torso(model, checker):
    through = _pose(model, shoulder_l__abduct="lo", shoulder_l__rotate=1.2, elbow_l__flex=0.1)
    r = checker.check(through)
    assert r.limb_in_torso.tolist() == [True] and r.plausible.tolist() == [False]
    beside = _pose(model, shoulder_l__abduct=0.0, shoulder_l__rotate=1.2, elbow_l__flex=0.1)
    assert checker.check(beside).plausible.tolist() == [True]
    # A larger margin (how deep a point must be) lets the same pose pass.
    assert PoseChecker(model, margin=0.5).check(through).plausible.tolist() == [True]


def test_batch_results_match_single_poses(model, checker):
    x = torch.randn(6, model.num_dofs, generator=torch.Generator().manual_seed(0)) * 1.5
    batch = checker.check(x)
    for i in range(6):
        one = checker.check(x[i : i + 1])
        assert one.plausible[0] == batch.plausible[i]
        np.testing.assert_allclose(one.foot_forward[0], batch.foot_forward[i], atol=1e-5)


def test_the_checked_points_are_the_full_models(model, checker):
    """The checker poses only the joints and the checked keypoints' vertices: they must be what a
    forward pass of the whole mean body gives."""
    from blsm.joint_limits import angles_from_unconstrained

    angles = angles_from_unconstrained(torch.randn(16, 47, generator=torch.Generator().manual_seed(5)), model.dof_limits)
    kp, joints, A = checker._skeleton(angles)
    full = copy.deepcopy(model).double()(angles=angles.double())
    need = checker._need
    assert torch.allclose(kp[:, need], full.keypoints[:, need], atol=1e-9)
    assert torch.allclose(joints, full.joints, atol=1e-9) and torch.allclose(A, full.skinning_transforms, atol=1e-9)
