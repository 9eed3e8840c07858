from __future__ import annotations

import numpy as np
import pytest
import torch

import blsm
from blsm.skeleton import mirror_name


def test_no_arguments_give_the_template_exactly(model):
    out = model()
    assert out.vertices.shape == (1, model.num_vertices, 3)
    assert torch.equal(out.vertices[0], model.template)
    assert torch.equal(out.joints[0], model.heads)


def test_zero_angles_and_zero_coefficients_give_the_template_exactly(model):
    b = 3
    out = model(
        angles=torch.zeros(b, 47),
        bone=torch.zeros(b, model.num_bone_coeffs),
        shape=torch.zeros(b, model.num_shape_coeffs),
    )
    assert torch.equal(out.vertices, model.template.expand(b, -1, -1))


def test_output_shapes_and_names(model, gen):
    b = 4
    out = model(
        pose=torch.randn(b, 47, generator=gen),
        bone=torch.randn(b, model.num_bone_coeffs, generator=gen),
        shape=torch.randn(b, model.num_shape_coeffs, generator=gen),
        global_orient=torch.randn(b, 3, generator=gen),
        transl=torch.randn(b, 3, generator=gen),
    )
    j, k = model.num_joints, len(model.keypoint_names)
    assert out.vertices.shape == (b, model.num_vertices, 3)
    assert out.joints.shape == (b, j, 3)
    assert out.keypoints.shape == (b, k, 3)
    assert out.angles.shape == (b, 47) and out.bone_scales.shape == (b, j)
    assert len(model.dof_names) == 47 and model.dof_limits.shape == (47, 2)
    assert len(model.bone_names) == len(model.parents) == j
    assert model.faces.shape[1] == 3 and model.uvs.shape[1] == 2
    assert model.vertex_parts.shape == (model.num_vertices,)
    assert set(model.part_names) >= {"head", "torso", "left_arm", "right_arm", "left_leg", "right_leg"}
    for name in ("nose", "left_eye", "right_ear", "left_shoulder", "right_ankle", "head_top", "knee_l"):
        assert name in model.keypoint_names
    assert len(model.keypoint_sets["coco17"]) == 17
    # Joint keypoints are the joints.
    ki = model.keypoint_names.index("left_knee")
    assert torch.equal(out.keypoints[:, ki], out.joints[:, model.bone_names.index("knee_l")])
    assert np.isfinite(out.vertices.detach().numpy()).all()


def test_atoms_inside_limits_and_midpoint_at_zero(model, gen):
    x = torch.randn(64, 47, generator=gen) * 10
    ang = model(pose=x).angles
    assert (ang >= model.dof_limits[:, 0]).all() and (ang <= model.dof_limits[:, 1]).all()
    mid = model(pose=torch.zeros(1, 47)).angles[0]
    assert torch.allclose(mid, model.dof_limits.mean(1), atol=1e-7)


def test_bone_scales_follow_eq4_and_joints_scale(model, gen):
    cb = torch.randn(2, model.num_bone_coeffs, generator=gen)
    out = model(bone=cb)
    assert torch.allclose(out.bone_scales, model.bone_mean + cb @ model.bone_basis)
    # With zero pose the length from a joint to its child scales with the joint's b.
    k = model.bone_names.index("knee_l")
    a = model.bone_names.index("ankle_l")
    rest = (model.heads[a] - model.heads[k]).norm()
    posed = (out.joints[:, a] - out.joints[:, k]).norm(dim=-1)
    assert torch.allclose(posed, out.bone_scales[:, k] * rest, rtol=1e-5)
    # rest_joints are the chain of Eq. 3 with identity rotations.
    from blsm.kinematics import forward_kinematics, local_scales

    eye = torch.eye(3).expand(2, model.num_joints, 3, 3)
    s = local_scales(out.bone_scales, model.parents_t)
    ref = forward_kinematics(eye, s, model.heads, model.frames, model.parents)[2]
    assert torch.allclose(out.rest_joints, ref, atol=1e-6)
    assert torch.allclose(out.rest_joints, out.joints, atol=1e-6)  # zero pose


def test_mirrored_pose_mirrors_the_mesh_within_1mm(model, gen):
    x = torch.randn(8, 47, generator=gen) * 1.5
    cb = torch.randn(8, model.num_bone_coeffs, generator=gen)
    cs = torch.randn(8, model.num_shape_coeffs, generator=gen)
    a = model(pose=x, bone=cb, shape=cs).vertices
    m = model(pose=model.mirror_pose(x), bone=cb, shape=cs).vertices
    reflected = a[:, model.vertex_mirror] * torch.tensor([-1.0, 1.0, 1.0])
    err = (m - reflected).norm(dim=-1).max()
    assert err < 1e-3, f"max mirror error {float(err) * 1000:.3f} mm"
    # The same holds for angles (mirror of angles is the angles of the mirror).
    ang = model(pose=x).angles
    assert torch.allclose(model.mirror_pose(ang), model(pose=model.mirror_pose(x)).angles, atol=1e-6)
    # Non-trivial: the mirrored pose differs from the pose.
    assert (model.mirror_pose(x) - x).abs().max() > 0.1


def test_joint_names_mirror_consistently(model):
    for name in model.bone_names + model.keypoint_names:
        assert mirror_name(name) in model.bone_names + model.keypoint_names


def test_angles_input_equals_pose_input(model, gen):
    x = torch.randn(3, 47, generator=gen)
    a = model(pose=x)
    b = model(angles=a.angles)
    assert torch.allclose(a.vertices, b.vertices, atol=1e-6)


def test_global_orient_rotates_about_the_root_and_transl_moves(model):
    r = torch.tensor([[0.0, torch.pi / 2, 0.0]])
    out = model(global_orient=r, transl=torch.tensor([[1.0, 2.0, 3.0]]))
    root = model.heads[0]
    assert torch.allclose(out.joints[0, 0], root + torch.tensor([1.0, 2.0, 3.0]), atol=1e-6)
    # +90 degrees about Y turns the body's front (+Z) towards +X.
    nose = model.keypoint_names.index("nose")
    rest = model().keypoints[0, nose] - root
    moved = out.keypoints[0, nose] - root - torch.tensor([1.0, 2.0, 3.0])
    assert torch.allclose(moved, torch.stack([rest[2], rest[1], -rest[0]]), atol=1e-5)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(pose=torch.zeros(2, 46)), r"pose must be \(B, 47\)"),
        (dict(pose=torch.zeros(47)), r"pose must be \(B, 47\)"),
        (dict(bone=torch.zeros(2, 3)), r"bone must be \(B, "),
        (dict(shape=torch.zeros(2, 999)), r"shape must be \(B, "),
        (dict(global_orient=torch.zeros(2, 4)), r"global_orient must be \(B, 3\)"),
        (dict(transl=torch.zeros(2, 3, dtype=torch.float64)), "transl must have the model's dtype"),
        (dict(pose=torch.zeros(2, 47, dtype=torch.int64)), "pose must have the model's dtype"),
        (dict(pose=torch.zeros(2, 47), transl=torch.zeros(3, 3)), "transl has batch size 3"),
        (dict(pose=torch.zeros(1, 47), angles=torch.zeros(1, 47)), "either pose"),
        (dict(pose=np.zeros((1, 47), dtype=np.float32)), "pose must be a torch.Tensor"),
    ],
)
def test_bad_inputs_raise_value_error_naming_the_argument(model, kwargs, match):
    with pytest.raises(ValueError, match=match):
        model(**kwargs)


def test_angles_outside_limits_are_an_error(model):
    ang = torch.zeros(1, 47)
    i = model.dof_names.index("knee_l.flex")
    ang[0, i] = -0.5  # a backwards knee
    with pytest.raises(ValueError, match="knee_l.flex"):
        model(angles=ang)


def test_float64_gradcheck_of_the_forward_pass(model64, gen):
    b = 1
    args = (
        torch.randn(b, 47, generator=gen, dtype=torch.float64) * 0.5,
        torch.randn(b, model64.num_bone_coeffs, generator=gen, dtype=torch.float64),
        torch.randn(b, model64.num_shape_coeffs, generator=gen, dtype=torch.float64),
        torch.randn(b, 3, generator=gen, dtype=torch.float64),
        torch.randn(b, 3, generator=gen, dtype=torch.float64),
    )
    args = tuple(a.requires_grad_() for a in args)
    idx = torch.arange(0, model64.num_vertices, 97)  # a subset of outputs keeps it fast

    def f(pose, bone, shape, r, t):
        out = model64(pose=pose, bone=bone, shape=shape, global_orient=r, transl=t)
        return out.vertices[:, idx], out.keypoints

    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-5)


def test_every_input_moves_the_mesh(model, gen):
    inputs = dict(
        pose=torch.randn(1, 47, generator=gen),
        bone=torch.randn(1, model.num_bone_coeffs, generator=gen),
        shape=torch.randn(1, model.num_shape_coeffs, generator=gen),
        global_orient=torch.randn(1, 3, generator=gen),
        transl=torch.randn(1, 3, generator=gen),
    )
    for t in inputs.values():
        t.requires_grad_()
    model(**inputs).vertices.square().sum().backward()
    for name, t in inputs.items():
        assert t.grad is not None and t.grad.abs().sum() > 0, name
    assert (inputs["pose"].grad.abs() > 0).all(), "every atom must move some vertex"


def test_float64_and_device_moves(model64):
    out = model64(pose=torch.zeros(2, 47, dtype=torch.float64))
    assert out.vertices.dtype == torch.float64
    if torch.cuda.is_available():
        m = blsm.load().cuda()
        assert m(pose=torch.zeros(2, 47, device="cuda")).vertices.is_cuda


def test_weights_and_template_are_well_formed(model):
    import trimesh

    w = model.weights
    assert (w >= 0).all() and torch.allclose(w.sum(1), torch.ones(model.num_vertices), atol=1e-5)
    mesh = trimesh.Trimesh(model.template.numpy(), model.faces.numpy(), process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.euler_number == 2
    assert mesh.volume > 0  # outward normals
    assert 5000 <= model.num_vertices <= 10000
    t = model.template
    assert torch.allclose(t[model.vertex_mirror] * torch.tensor([-1.0, 1.0, 1.0]), t, atol=1e-6)
    # Y up, facing +Z: the head is above the feet and the toes point forward.
    kp = dict(zip(model.keypoint_names, model().keypoints[0]))
    assert kp["head_top"][1] > kp["ankle_l"][1] + 1.0
    assert kp["toe_tip_l"][2] > kp["heel_l"][2] + 0.1
    assert kp["nose"][2] > kp["head"][2]
    assert kp["knee_l"][0] > 0  # +X is the body's left
    assert 0.0 <= float(model.uvs.min()) and float(model.uvs.max()) <= 1.0


def test_shape_decoder_hook(model, gen):
    class Double(torch.nn.Module):
        num_coeffs = model.num_shape_coeffs

        def forward(self, c):
            return 2 * model.shape_decoder(c)

    m = blsm.load()
    cs = torch.randn(1, m.num_shape_coeffs, generator=gen)
    ref = m(shape=2 * cs).vertices
    m.set_shape_decoder(Double())
    assert torch.allclose(m(shape=cs).vertices, ref, atol=1e-6)
