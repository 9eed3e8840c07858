"""Each atom moves the right body part the anatomically right way (paper 000 Fig. 2)."""

from __future__ import annotations

import pytest
import torch


def _move(model, dof: str, keypoint: str, frac: float) -> torch.Tensor:
    i = model.dof_names.index(dof)
    lo, hi = model.dof_limits[i]
    a = torch.zeros(1, 47)
    a[0, i] = hi * frac if frac > 0 else lo * -frac
    k = model.keypoint_names.index(keypoint)
    return model(angles=a).keypoints[0, k] - model().keypoints[0, k]


X, Y, Z = 0, 1, 2
# (atom, keypoint that must move, world axis, sign of its motion for a positive angle)
CASES = [
    ("knee_{s}.flex", "ankle_{s}", Z, -1),  # the shin swings backwards
    ("elbow_{s}.flex", "wrist_{s}", Y, +1),  # the forearm comes up (rest arm hangs down)
    ("hip_{s}.flex", "knee_{s}", Z, +1),  # the thigh swings forwards
    ("hip_{s}.abduct", "knee_{s}", X, "out"),
    ("hip_{s}.rotate", "toe_tip_{s}", X, "in"),  # internal rotation turns the toes inwards
    ("shoulder_{s}.abduct", "elbow_{s}", Y, +1),
    ("shoulder_{s}.flex", "elbow_{s}", Z, +1),
    ("shoulder_{s}.rotate", "hand_tip_{s}", X, "in"),  # internal rotation brings the hand to the belly
    ("clavicle_{s}.elevate", "shoulder_{s}", Y, +1),
    ("clavicle_{s}.protract", "shoulder_{s}", Z, +1),
    ("ankle_{s}.plantarflex", "toe_tip_{s}", Y, -1),
    ("ankle_{s}.abduct", "toe_tip_{s}", X, "out"),
    ("spine_01.flex", "head_top", Z, +1),
    ("spine_02.side_bend", "head_top", X, +1),  # towards the body's left
    ("neck.twist", "nose", X, +1),  # the face turns to the body's left
    ("head.flex", "nose", Y, -1),  # nodding down
]


@pytest.mark.parametrize("side", ["l", "r"])
@pytest.mark.parametrize("dof, kp, axis, sign", CASES)
def test_positive_atoms_move_the_named_way(model, side, dof, kp, axis, sign):
    dof, kp = dof.format(s=side), kp.format(s=side)
    if sign in ("out", "in"):
        lateral = 1 if side == "l" else -1  # +X is the body's left
        sign = lateral if sign == "out" else -lateral
    d = _move(model, dof, kp, 0.8)
    assert float(d[axis]) * sign > 0.02, f"{dof} moved {kp} by {d.tolist()}"


@pytest.mark.parametrize("side", ["l", "r"])
def test_knees_and_elbows_never_bend_backwards(model, side):
    for joint, parent, child in (("knee", "hip", "ankle"), ("elbow", "shoulder", "wrist")):
        i = model.dof_names.index(f"{joint}_{side}.flex")
        kp = model.keypoint_names
        for theta in torch.linspace(float(model.dof_limits[i, 0]), float(model.dof_limits[i, 1]), 9):
            a = torch.zeros(1, 47)
            a[0, i] = theta
            k = model(angles=a).keypoints[0]
            upper = k[kp.index(f"{joint}_{side}")] - k[kp.index(f"{parent}_{side}")]
            lower = k[kp.index(f"{child}_{side}")] - k[kp.index(f"{joint}_{side}")]
            # Flexion axis: the frame's x axis (lateral for legs, down/up for arms).
            axis = model.frames[model.bone_names.index(f"{joint}_{side}")][:, 0]
            bend = torch.dot(torch.linalg.cross(upper, lower), axis)
            assert bend > -0.02 * upper.norm() * lower.norm(), f"{joint}_{side} bends backwards at {theta}"


@pytest.mark.parametrize("side", ["l", "r"])
def test_wrist_flexion_moves_fingers_to_the_palm(model, side):
    # Palm normal from the hand's surface: n = d x r for the left hand (d: wrist to fingertip,
    # r: towards the thumb); mirrored for the right. Thumb side is where the radial deviation goes.
    kp = model.keypoint_names
    rest = model().keypoints[0]
    d = rest[kp.index(f"hand_tip_{side}")] - rest[kp.index(f"wrist_{side}")]
    flex = _move(model, f"wrist_{side}.flex", f"hand_tip_{side}", 0.8)
    dev = _move(model, f"wrist_{side}.deviate", f"hand_tip_{side}", 0.8)
    normal = torch.linalg.cross(d, dev) * (1 if side == "l" else -1)
    # Anny's palms face the body (medial) in the rest pose.
    lateral = 1 if side == "l" else -1
    assert float(normal[X]) * lateral < 0
    assert torch.dot(flex, normal) > 0
