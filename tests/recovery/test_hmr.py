"""recovery.models.hmr and recovery.utils.geometry: the IEF regressor, decoding, Theta_0, the camera."""

from __future__ import annotations

import pytest
import torch

from recovery.models.heads import ParamLayout, mean_theta
from recovery.models.hmr import HMRBLSM, body_outputs
from recovery.utils.geometry import (
    UPRIGHT_FACING_CAMERA,
    cam_to_translation,
    matrix_to_rot6d,
    project,
    rot6d_to_matrix,
    translation_to_cam,
)


def _network(model, iterations: int, gen: torch.Generator) -> HMRBLSM:
    layout = ParamLayout(model.num_dofs, model.num_bone_coeffs, 4)
    init = torch.randn(
        layout.size, generator=gen
    )  # a Theta_0 far from zero, so that "equals" means something
    init[layout.slices()["cam"]] = torch.tensor([0.9, 0.1, -0.05])
    net = HMRBLSM(
        "resnet18", layout, model.num_shape_coeffs, init, hidden=16, dropout=0.0, iterations=iterations
    )
    return net.eval()


def test_zero_ief_iterations_give_the_mean_parameters(model, gen):
    net = _network(model, 0, gen)
    init = net.regressor.init
    lay = net.layout.slices()
    for images in (torch.rand(3, 3, 32, 32, generator=gen), torch.zeros(3, 3, 32, 32)):
        with torch.no_grad():
            out = net(images)
        assert out.thetas.shape == (1, 3, net.layout.size)
        assert torch.equal(out.thetas[0], init.expand(3, -1))
        assert torch.equal(out.pose, init[lay["pose"]].expand(3, -1))
        assert torch.equal(out.bone, init[lay["bone"]].expand(3, -1))
        assert torch.equal(out.cam, init[lay["cam"]].expand(3, -1))
        assert out.shape.shape == (3, model.num_shape_coeffs)
        assert torch.equal(out.shape[:, :4], init[lay["shape"]].expand(3, -1))
        assert torch.equal(out.shape[:, 4:], torch.zeros(3, model.num_shape_coeffs - 4))
        assert torch.equal(out.orient, rot6d_to_matrix(init[lay["orient"]][None]).expand(3, -1, -1))


def test_zero_ief_iterations_from_the_config(model, gen):
    from recovery.config import ModelConfig, RecoveryConfig
    from recovery.models.registry import build_hmr

    cfg = RecoveryConfig(
        model=ModelConfig(backbone="resnet18", pretrained=False, ief_iterations=0, hidden=16)
    )
    init = torch.randn(ParamLayout(model.num_dofs, model.num_bone_coeffs, 10).size, generator=gen)
    net = build_hmr(cfg, model, init).train()  # dropout and batch statistics change nothing either
    with torch.no_grad():
        out = net(torch.rand(2, 3, 32, 32, generator=gen))
    assert torch.equal(out.thetas, init.expand(1, 2, -1))


def test_ief_iterations_refine_from_the_mean(model, gen):
    net = _network(model, 3, gen)
    images = torch.rand(2, 3, 32, 32, generator=gen)
    with torch.no_grad():
        out = net(images)
    assert out.thetas.shape == (4, 2, net.layout.size)
    assert torch.equal(out.thetas[0], net.regressor.init.expand(2, -1))
    step = (out.thetas[1:] - out.thetas[:-1]).abs().amax(-1)
    assert (step > 0).all()  # every iteration moves ...
    assert (step < 0.5).all()  # ... a little: the last layer starts near 0 (SPIN)
    assert not torch.equal(out.thetas[-1, 0], out.thetas[-1, 1])  # and depends on the image
    assert torch.equal(out.pose, out.thetas[-1][:, net.layout.slices()["pose"]])


def test_bad_init_is_an_error(model):
    layout = ParamLayout(model.num_dofs, model.num_bone_coeffs, 4)
    with pytest.raises(ValueError, match=rf"init must be \({layout.size},\)"):
        HMRBLSM("resnet18", layout, model.num_shape_coeffs, torch.zeros(layout.size + 1))


def test_mean_theta_is_the_label_mean_facing_the_camera(model, gen):
    layout = ParamLayout(model.num_dofs, model.num_bone_coeffs, 4)
    pose, bone = torch.randn(5, 47, generator=gen), torch.randn(5, model.num_bone_coeffs, generator=gen)
    shape, cam = torch.randn(5, model.num_shape_coeffs, generator=gen), torch.rand(5, 3, generator=gen)
    p = layout.split(mean_theta(layout, pose, bone, shape, cam))
    torch.testing.assert_close(p["pose"], pose.mean(0))
    torch.testing.assert_close(p["bone"], bone.mean(0))
    torch.testing.assert_close(p["shape"], shape[:, :4].mean(0))
    torch.testing.assert_close(p["cam"], cam.mean(0))
    torch.testing.assert_close(rot6d_to_matrix(p["orient"][None])[0], UPRIGHT_FACING_CAMERA)
    # Upright and facing the camera: the rest body's up (+Y) is the image's up (-y), its front (+Z)
    # points at the camera (-z).
    out = body_outputs(
        model,
        torch.zeros(1, 47),
        UPRIGHT_FACING_CAMERA[None],
        torch.zeros(1, model.num_bone_coeffs),
        torch.zeros(1, model.num_shape_coeffs),
    )
    names = model.keypoint_names
    assert out.keypoints_3d[0, names.index("head_top"), 1] < -0.3


def test_rot6d_round_trip(gen):
    q, _ = torch.linalg.qr(torch.randn(6, 3, 3, generator=gen, dtype=torch.float64))
    r = q * torch.linalg.det(q)[:, None, None]
    torch.testing.assert_close(rot6d_to_matrix(matrix_to_rot6d(r)), r)
    # Gram-Schmidt: any 6 numbers give a rotation.
    m = rot6d_to_matrix(torch.randn(6, 6, generator=gen, dtype=torch.float64))
    torch.testing.assert_close(m @ m.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(6, 3, 3))
    torch.testing.assert_close(torch.linalg.det(m), torch.ones(6, dtype=torch.float64))


def test_camera_round_trip_and_meaning(gen):
    crop = 64
    k = torch.tensor([[[300.0, 0.0, 30.0], [0.0, 310.0, 35.0], [0.0, 0.0, 1.0]]], dtype=torch.float64).expand(
        4, 3, 3
    )
    cam = torch.tensor(
        [[0.8, 0.0, 0.0], [1.2, 0.3, -0.2], [0.5, -0.5, 0.4], [2.0, 0.1, 0.1]], dtype=torch.float64
    )
    t = cam_to_translation(cam, k, crop)
    torch.testing.assert_close(translation_to_cam(t, k, crop), cam)
    # (tx, ty) is where the pelvis projects, s the weak-perspective scale 2 f / (S z).
    uv = project(t[:, None], k)[:, 0]
    torch.testing.assert_close(uv, crop / 2 * (1 + cam[:, 1:]))
    torch.testing.assert_close(t[:, 2], 2 * 305.0 / (crop * cam[:, 0]))
