"""Posing any template on the BLSM skeleton with per-bone scales (thesis Eqs. 5.3-5.6, 5.12).

``BLSM.forward`` takes bone *coefficients* (Eq. 5.4). Learning the model needs the same chain with
the bone scales ``b`` themselves as unknowns (Eq. 5.13 fits ``s`` before any bone basis exists), a
template and weights other than the model's (Eqs. 5.27, 5.30), and per-body joint positions (the
SMPL-type baseline regresses its joints from vertices). :func:`pose` is that forward pass.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from blsm.joint_limits import angles_from_unconstrained
from blsm.kinematics import forward_kinematics, joint_rotations, local_scales
from blsm.lbs import linear_blend_skinning


@dataclass
class Posed:
    """Result of :func:`pose`.

    Attributes:
        vertices: (B, V, 3) posed vertices (Eq. 5.12).
        joints: (B, J, 3) posed joint (bone head) positions.
        transforms: (B, J, 3, 4) skinning transforms ``[L_j | t_j]``.
        angles: (B, 47) atom angles in radians.
    """

    vertices: torch.Tensor
    joints: torch.Tensor
    transforms: torch.Tensor
    angles: torch.Tensor


def pose(
    model,
    template: torch.Tensor,
    bone_scales: torch.Tensor | None = None,
    pose: torch.Tensor | None = None,
    angles: torch.Tensor | None = None,
    global_orient: torch.Tensor | None = None,
    transl: torch.Tensor | None = None,
    weights: torch.Tensor | None = None,
    heads: torch.Tensor | None = None,
) -> Posed:
    """LBS of ``template`` on ``model``'s skeleton.

    Args:
        model: a :class:`blsm.BLSM` (skeleton, frames, DoF table, limits, default weights).
        template: (B, V, 3) or (V, 3) rest vertices.
        bone_scales: (B, J) global bone scales b (Eq. 5.4's left side); None means the model's mean.
        pose: (B, 47) unconstrained atom values (Eq. 5.6), or ``angles`` (B, 47) radians; neither
            means the rest pose.
        global_orient: (B, 3) axis-angle about the root joint; transl: (B, 3) metres.
        weights: (V, J) blend weights; None means the model's.
        heads: (J, 3) or (B, J, 3) bind-pose joint positions; None means the model's.

    Returns:
        :class:`Posed`.
    """
    if pose is not None and angles is not None:
        raise ValueError("give either pose (unconstrained) or angles (radians), not both")
    dtype, device = model.template.dtype, model.template.device
    batch = 1
    for t in (template if template.dim() == 3 else None, bone_scales, pose, angles, global_orient, transl, heads if heads is not None and heads.dim() == 3 else None):
        if t is not None:
            batch = max(batch, t.shape[0])
    if pose is not None:
        theta = angles_from_unconstrained(pose, model.dof_limits)
    elif angles is not None:
        theta = angles
    else:
        theta = torch.zeros(batch, model.num_dofs, dtype=dtype, device=device)
    theta = theta.expand(batch, -1)
    b = model.bone_mean.expand(batch, -1) if bone_scales is None else bone_scales.expand(batch, -1)
    s = local_scales(b, model.parents_t)  # Eq. 5.5
    rot = joint_rotations(theta, model.dof_slots, model.dof_axis, model.dof_sign)
    g_rot = None
    if global_orient is not None:
        from kornia.geometry.conversions import axis_angle_to_rotation_matrix

        g_rot = axis_angle_to_rotation_matrix(global_orient.expand(batch, -1))
    h = model.heads if heads is None else heads
    linear, offset, joints = forward_kinematics(
        rot, s, h, model.frames, model.parents, g_rot, None if transl is None else transl.expand(batch, -1)
    )
    w = model.weights if weights is None else weights
    tmpl = template.expand(batch, -1, -1) if template.dim() == 3 else template.expand(batch, -1, -1)
    vertices = linear_blend_skinning(tmpl, w, linear, offset)
    return Posed(vertices, joints, torch.cat([linear, offset[..., None]], dim=-1), theta)
