"""Skeleton synthesis: bone scales (Eqs. 4, 5), joint rotations (Eq. 6 -> R) and the chain (Eq. 3).

Conventions: metres, radians, Y up, body facing +Z at rest. All functions are pure, batched and
differentiable; they work in float32 and float64 on any device.

The chain is evaluated directly as the skinning transforms ``A_j = T_j \\hat{T}_j^{-1}`` of Eq. 12.
With the bind frame ``Q_j`` and head ``h_j`` of bone j (see :mod:`blsm.skeleton`) the local transform
of Eq. 3, written with the deformation in the bone's own frame, ``T^j = [R^t_j, O^t_j] [s_j R_j, 0]``,
gives ``A_j = A_parent(j) K_j`` with the similarity about the joint

    K_j = [ s_j Q_j R_j Q_j^T | h_j - s_j Q_j R_j Q_j^T h_j ].

The scale s_j of bone j therefore scales the offsets of its children, and the product of s along a
chain is the bone scale b of Eq. 4 (Eq. 5). The rotation of joint j moves bone j and its subtree.
Rotations are built as ``I + Q (R - I) Q^T`` so that the rest pose gives the identity exactly.
"""

from __future__ import annotations

import functools

import torch


def axis_rotations(theta: torch.Tensor, axis: torch.Tensor, sign: torch.Tensor) -> torch.Tensor:
    """Rotation matrices about signed coordinate axes.

    Args:
        theta: (..., D) angles in radians.
        axis: (D,) long, 0/1/2 for x/y/z (or any shape matching the trailing dims of theta).
        sign: (D,) +1 or -1, the direction of the axis (same shape as axis).

    Returns:
        (..., D, 3, 3) rotations by ``theta`` about ``sign * e_axis``; exactly I where theta == 0.
    """
    t = theta * sign.to(theta.dtype)
    c, s = torch.cos(t), torch.sin(t)
    one, zero = torch.ones_like(t), torch.zeros_like(t)
    # Rows of R_x, R_y, R_z for a right-handed rotation by t.
    rx = torch.stack([one, zero, zero, zero, c, -s, zero, s, c], dim=-1)
    ry = torch.stack([c, zero, s, zero, one, zero, -s, zero, c], dim=-1)
    rz = torch.stack([c, -s, zero, s, c, zero, zero, zero, one], dim=-1)
    a = axis.reshape((1,) * (t.dim() - axis.dim()) + tuple(axis.shape) + (1,))
    rot = torch.where(a == 0, rx, torch.where(a == 1, ry, rz))
    return rot.reshape(*t.shape, 3, 3)


def joint_rotations(
    theta: torch.Tensor,
    slots: torch.Tensor,
    axis: torch.Tensor,
    sign: torch.Tensor,
) -> torch.Tensor:
    """Compose the single-axis atoms of each joint into one rotation per bone (Eq. 6 -> R).

    Args:
        theta: (B, D) atom angles in radians.
        slots: (J, S) long, the atoms of each bone in composition order, padded with D (identity).
        axis: (D,) long, the axis of each atom.
        sign: (D,) the axis sign of each atom.

    Returns:
        (B, J, 3, 3) rotations ``R_j = R_slot0 @ R_slot1 @ ...`` in each bone's bind frame.
    """
    batch = theta.shape[0]
    pad = torch.zeros(batch, 1, dtype=theta.dtype, device=theta.device)
    theta_p = torch.cat([theta, pad], dim=1)  # (B, D + 1)
    axis_p = torch.cat([axis, axis.new_zeros(1)])
    sign_p = torch.cat([sign, sign.new_ones(1)])
    rots = axis_rotations(theta_p[:, slots], axis_p[slots], sign_p[slots])  # (B, J, S, 3, 3)
    out = rots[:, :, 0]
    for k in range(1, slots.shape[1]):
        out = out @ rots[:, :, k]
    return out


def bone_scales(coeffs: torch.Tensor, mean: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
    """Eq. 4: ``b = b_mean + c_b P_b``.

    Args:
        coeffs: (B, Kb) bone coefficients (in standard deviations of the training population).
        mean: (J,) mean bone scale (ones for a model built as in Sec. 4.2).
        basis: (Kb, J) bone-scale basis.

    Returns:
        (B, J) global bone scales b.
    """
    return mean + coeffs @ basis


def local_scales(b: torch.Tensor, parents: torch.Tensor) -> torch.Tensor:
    """Eq. 5: ``s_i = b_i / b_parent(i)``, and ``s_root = b_root``.

    The paper fixes ``s_0 = 1`` because its root scale is 1; keeping ``b_root`` makes the product of
    s along every chain equal b for any model.

    Args:
        b: (B, J) global bone scales.
        parents: (J,) long, parent index of each bone, -1 for the root.

    Returns:
        (B, J) local scales s.
    """
    par = parents.clamp(min=0)
    denom = torch.where(parents[None] < 0, torch.ones_like(b), b[:, par])
    return b / denom


def rest_joints(b: torch.Tensor, heads: torch.Tensor, parents: torch.Tensor, chain: torch.Tensor) -> torch.Tensor:
    """The bind-pose joints of a person with global bone scales ``b`` (scaled bones, no rotation).

    Each bone's offset to its parent scales with the parent's ``b``, so a joint is the root plus the
    scaled offsets along its chain.

    Args:
        b: (B, J) global bone scales.
        heads: (J, 3) the template's joint positions.
        parents: (J,) long, parent index of each bone, -1 for the root.
        chain: (J, J) ``chain[j, k] = 1`` for every non-root bone ``k`` on the path root -> ``j``.

    Returns:
        (B, J, 3) rest joints.
    """
    par = parents.clamp(min=0)
    scaled = b[:, par, None] * (heads - heads[par])
    return heads[0] + torch.einsum("jk,bkc->bjc", chain, scaled)


@functools.lru_cache(maxsize=32)
def tree_levels(parents: tuple[int, ...]) -> list[tuple[list[int], list[int]]]:
    """Bones grouped by depth: [(indices, parent indices)], the first level being the root."""
    depth = []
    for j, p in enumerate(parents):
        if p >= j:
            raise ValueError(f"parents must precede children (bone {j} has parent {p})")
        depth.append(0 if p < 0 else depth[p] + 1)
    if depth.count(0) != 1:
        raise ValueError("the bone tree must have exactly one root")
    out = []
    for d in range(max(depth) + 1):
        idx = [j for j in range(len(parents)) if depth[j] == d]
        out.append((idx, [max(parents[j], 0) for j in idx]))
    return out


def forward_kinematics(
    rotations: torch.Tensor,
    scales: torch.Tensor,
    heads: torch.Tensor,
    frames: torch.Tensor,
    parents: list[int],
    global_rotation: torch.Tensor | None = None,
    transl: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Chain product of Eq. 3, returned as the skinning transforms ``A_j = T_j T^_j^{-1}`` (Eq. 12).

    Args:
        rotations: (B, J, 3, 3) joint rotations R_j in bind-frame coordinates.
        scales: (B, J) local scales s_j (Eq. 5).
        heads: (J, 3) bind-pose joint positions in metres, or (B, J, 3) per body.
        frames: (J, 3, 3) bind frames Q_j (columns are axes in world coordinates).
        parents: parent index per bone, -1 for the root; parents precede children.
        global_rotation: optional (B, 3, 3) rotation of the whole body about the root joint.
        transl: optional (B, 3) translation in metres, applied after the global rotation.

    Returns:
        linear: (B, J, 3, 3) linear part L_j of A_j (rotation times the bone's scale b_j).
        offset: (B, J, 3) translation part of A_j.
        joints: (B, J, 3) posed joint (bone head) positions ``A_j h_j``.
    """
    eye = torch.eye(3, dtype=rotations.dtype, device=rotations.device)
    # Q (R - I) Q^T is exactly 0 where R is exactly I, so the rest pose stays exact.
    local = eye + frames @ (rotations - eye) @ frames.transpose(-1, -2)  # (B, J, 3, 3)
    local = scales[..., None, None] * local
    t_local = heads - (local @ heads[..., None])[..., 0]  # (B, J, 3)
    levels = tree_levels(tuple(parents))
    root = levels[0][0]
    l_root, t_root = local[:, root], t_local[:, root]
    if global_rotation is not None:
        l_root = global_rotation[:, None] @ l_root
        h_root = heads[..., root, :]
        t_root = h_root - (l_root @ h_root[..., None])[..., 0]
    if transl is not None:
        t_root = t_root + transl[:, None]
    linear = local.index_copy(1, torch.as_tensor(root, device=local.device), l_root)
    offset = t_local.index_copy(1, torch.as_tensor(root, device=local.device), t_root)
    # One batched product per tree level (parents are final once their level is done).
    for idx, par in levels[1:]:
        idx_t = torch.as_tensor(idx, device=local.device)
        lp = linear[:, par]
        linear = linear.index_copy(1, idx_t, lp @ local[:, idx])
        offset = offset.index_copy(1, idx_t, (lp @ t_local[:, idx, :, None])[..., 0] + offset[:, par])
    joints = (linear @ heads[..., None])[..., 0] + offset
    return linear, offset, joints
