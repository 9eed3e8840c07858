from __future__ import annotations

import torch

from blsm.kinematics import axis_rotations, forward_kinematics, joint_rotations, local_scales


def _random_frames(n, gen):
    q, _ = torch.linalg.qr(torch.randn(n, 3, 3, generator=gen, dtype=torch.float64))
    return q * torch.sign(torch.linalg.det(q))[:, None, None]


def test_eq5_chain_product_of_local_scales_is_b(model, gen):
    b = 1 + 0.2 * torch.randn(8, model.num_joints, generator=gen, dtype=torch.float64)
    s = local_scales(b, model.parents_t)
    for j in range(model.num_joints):
        prod = torch.ones(8, dtype=torch.float64)
        k = j
        while k >= 0:
            prod = prod * s[:, k]
            k = model.parents[k]
        assert torch.allclose(prod, b[:, j], rtol=1e-12)


def test_axis_rotations_are_rotations_and_exact_identity_at_zero(gen):
    theta = torch.randn(4, 6, generator=gen, dtype=torch.float64)
    axis = torch.tensor([0, 1, 2, 0, 1, 2])
    sign = torch.tensor([1.0, 1.0, 1.0, -1.0, -1.0, -1.0], dtype=torch.float64)
    r = axis_rotations(theta, axis, sign)
    eye = torch.eye(3, dtype=torch.float64)
    assert torch.allclose(r @ r.transpose(-1, -2), eye.expand_as(r), atol=1e-12)
    assert torch.allclose(torch.linalg.det(r), torch.ones(4, 6, dtype=torch.float64))
    z = axis_rotations(torch.zeros(1, 6, dtype=torch.float64), axis, sign)
    assert torch.equal(z, eye.expand_as(z))
    # Right-handed: +90 degrees about z maps x to y.
    rz = axis_rotations(torch.tensor([[torch.pi / 2]]), torch.tensor([2]), torch.tensor([1.0]))
    assert torch.allclose(rz[0, 0] @ torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]), atol=1e-6)


def test_joint_rotations_compose_in_table_order(gen):
    theta = torch.randn(2, 3, generator=gen, dtype=torch.float64)
    axis = torch.tensor([0, 2, 1])
    sign = torch.ones(3, dtype=torch.float64)
    slots = torch.tensor([[0, 1, 2], [3, 3, 3]])  # bone 0 has atoms 0,1,2; bone 1 none
    r = joint_rotations(theta, slots, axis, sign)
    single = axis_rotations(theta, axis, sign)
    assert torch.allclose(r[:, 0], single[:, 0] @ single[:, 1] @ single[:, 2])
    assert torch.equal(r[:, 1], torch.eye(3, dtype=torch.float64).expand(2, 3, 3))


def naive_chain(rot, s, heads, frames, parents):
    """Eq. 3 literally with 4x4 matrices: T^j = [R^t_j O^t_j] [s_j R_j 0], T_j = prod, A = T T^-1."""
    batch, nj = s.shape
    out = torch.zeros(batch, nj, 4, 4, dtype=rot.dtype)
    for bidx in range(batch):
        g = [None] * nj
        g_bind = [None] * nj
        for j, p in enumerate(parents):
            bind = torch.eye(4, dtype=rot.dtype)
            if p < 0:
                bind[:3, :3] = frames[j]
                bind[:3, 3] = heads[j]
            else:
                bind[:3, :3] = frames[p].T @ frames[j]  # R^t
                bind[:3, 3] = frames[p].T @ (heads[j] - heads[p])  # O^t
            deform = torch.eye(4, dtype=rot.dtype)
            deform[:3, :3] = s[bidx, j] * rot[bidx, j]
            local = bind @ deform
            local_bind = bind
            g[j] = local if p < 0 else g[p] @ local
            g_bind[j] = local_bind if p < 0 else g_bind[p] @ local_bind
            out[bidx, j] = g[j] @ torch.linalg.inv(g_bind[j])
    return out


def test_chain_matches_a_literal_eq3_product(model, gen):
    nj = model.num_joints
    heads = model.heads.double()
    frames = _random_frames(nj, gen)
    rot = _random_frames(3 * nj, gen).reshape(3, nj, 3, 3)
    s = 1 + 0.1 * torch.randn(3, nj, generator=gen, dtype=torch.float64)
    lin, off, joints = forward_kinematics(rot, s, heads, frames, model.parents)
    ref = naive_chain(rot, s, heads, frames, model.parents)
    assert torch.allclose(lin, ref[..., :3, :3], atol=1e-10)
    assert torch.allclose(off, ref[..., :3, 3], atol=1e-10)
    assert torch.allclose(joints, (ref[..., :3, :3] @ heads[..., None])[..., 0] + ref[..., :3, 3], atol=1e-10)


def test_fk_gradcheck(model, gen):
    nj = model.num_joints
    heads = model.heads.double()
    frames = _random_frames(nj, gen)
    theta = torch.randn(2, 47, generator=gen, dtype=torch.float64, requires_grad=True)
    s = (1 + 0.1 * torch.randn(2, nj, generator=gen, dtype=torch.float64)).requires_grad_()
    m = model

    def f(theta, s):
        rot = joint_rotations(theta, m.dof_slots, m.dof_axis, m.dof_sign.double())
        return forward_kinematics(rot, s, heads, frames, m.parents)[2]

    assert torch.autograd.gradcheck(f, (theta, s))
