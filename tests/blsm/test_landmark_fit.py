"""Tests of blsm/learn/registration/landmark_fit.py: the landmark fit of the registration (thesis Eq. 5.13)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from synthetic_scans import fps_vertices

from blsm.learn.posing import pose
from blsm.learn.registration.landmark_fit import (
    LandmarkSelection,
    fit_landmarks,
    pose_angles,
    read_landmark_definitions,
)
from blsm.learn.registration.register import st1_vertices
from blsm.learn.registration.register_config import RegisterConfig

pytestmark = pytest.mark.usefixtures("one_thread")


def test_stage1_recovers_pose_and_scales(model, gen):
    idx = fps_vertices(model.template, 250)
    sel = LandmarkSelection.from_index([str(i) for i in idx], idx)
    b_true = 1.0 + 0.15 * (torch.rand(2, model.num_joints, generator=gen) - 0.5)
    x_true = 0.3 * torch.randn(2, model.num_dofs, generator=gen)
    theta_true = pose_angles(model, x_true)
    go = torch.tensor([[0.2, 1.0, -0.1], [0.0, -0.5, 0.1]])
    tr = torch.tensor([[0.1, 0.9, -0.3], [-0.2, 1.0, 0.4]])
    with torch.no_grad():
        v_true = pose(model, model.template, bone_scales=b_true, angles=theta_true, global_orient=go, transl=tr).vertices
    lms = sel.select(v_true)
    lms[1, :10] = float("nan")  # unlocated landmarks are ignored
    cfg = RegisterConfig(stage1_iterations=800, angle_prior=0.0, scale_prior=0.0, shape_init=False)
    st = fit_landmarks(model, lms, sel, cfg)
    assert float(st.landmark_error.max()) < 1e-3  # metres
    v_fit = torch.stack([torch.as_tensor(st1_vertices(model, st, n)) for n in range(2)])
    assert float((v_fit - v_true).norm(dim=-1).mean()) < 2e-3
    # Bones carrying enough landmarks recover their scales.
    np.testing.assert_allclose(st.bone_scales[:, :4].numpy(), b_true[:, :4].numpy(), rtol=0.03)
    np.testing.assert_allclose(st.bone_scales[:, 14:].numpy(), b_true[:, 14:].numpy(), rtol=0.03)
    lo, hi = model.dof_limits[:, 0], model.dof_limits[:, 1]
    assert bool(((st.angles >= lo) & (st.angles <= hi)).all())


def test_stage1_bad_input(model, selection):
    sel = selection
    with pytest.raises(ValueError, match="landmarks must be"):
        fit_landmarks(model, torch.zeros(1, 5, 3), sel)
    with pytest.raises(ValueError, match="at least 3"):
        fit_landmarks(model, torch.full((1, len(sel), 3), float("nan")), sel)
    with pytest.raises(ValueError, match="landmark index"):
        LandmarkSelection.from_index(["a", "b"], [1, 2, 3])


def test_landmark_definitions_file(model, tmp_path):
    path = tmp_path / "lm.yaml"
    path.write_text("landmarks:\n  a: {vertex: 3}\n  b: {face: 7, bary: [0.2, 0.3, 0.5]}\n")
    sel = read_landmark_definitions(path, model)
    assert sel.names == ["a", "b"] and sel.vertices[0].tolist() == [3, 3, 3]
    assert sel.vertices[1].tolist() == model.faces[7].tolist()
    torch.testing.assert_close(sel.bary[1], torch.tensor([0.2, 0.3, 0.5]))
    path.write_text(f"a: {{vertex: {model.num_vertices}}}\n")
    with pytest.raises(ValueError, match="lm.yaml: a: bad landmark"):
        read_landmark_definitions(path, model)
