"""The Bone-Level Skinned Model as a thin ``nn.Module`` (paper 000 Sec. 3, Eqs. 1-12).

    model = blsm.load()
    out = model(pose=x, bone=cb, shape=cs, global_orient=r, transl=t)

Units and conventions: metres, radians, Y up, the body faces +Z at rest, +X is the body's left.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from blsm import io
from blsm.joint_limits import DofTable, angles_from_unconstrained, parse_dof_table
from blsm.kinematics import (
    bone_scales,
    forward_kinematics,
    joint_rotations,
    local_scales,
    rest_joints,
    tree_levels,
)
from blsm.lbs import blend_shapes, linear_blend_skinning, linear_shape

DEFAULT_MODEL = Path(__file__).parent / "data" / "blsm_anny_v1.npz"
"""The packaged model: ``blsm train configs/blsm/train_default.yaml`` (``make model``)."""
DEFAULT_RIG = Path(__file__).parent / "data" / "blsm_anny_rig.npz"
"""The packaged rig the model is learnt from: template (on the mean Anny body), skeleton, blend
weights, no blendshapes (``blsm build-anny --rig``). It fixes the topology, and with it the
ground-truth correspondence of Anny stand-in scans (:mod:`blsm.learn.scans.population`)."""


@dataclass
class BLSMOutput:
    """Result of a BLSM forward pass (all in metres / radians, world frame).

    Attributes:
        vertices: (B, V, 3) posed mesh (Eq. 2).
        joints: (B, J, 3) posed joint (bone head) positions, in ``bone_names`` order.
        keypoints: (B, K, 3) named keypoints, in ``keypoint_names`` order.
        angles: (B, 47) atom angles in radians (Eq. 6 applied to ``pose``).
        bone_scales: (B, J) global bone scales b (Eq. 4).
        template: (B, V, 3) the person's rest template V (Eq. 1) before skinning.
        rest_joints: (B, J, 3) the person's joints in the bind pose (bones scaled, no rotation).
        skinning_transforms: (B, J, 3, 4) ``A_j = T_j T^_j^{-1}`` of Eq. 12.
    """

    vertices: torch.Tensor
    joints: torch.Tensor
    keypoints: torch.Tensor
    angles: torch.Tensor
    bone_scales: torch.Tensor
    template: torch.Tensor
    rest_joints: torch.Tensor
    skinning_transforms: torch.Tensor


class LinearShapeDecoder(nn.Module):
    """Eq. 8, ``V_s = c_s P_s``; the default shape decoder.

    Any module with ``num_coeffs`` and ``forward(coeffs (B, Ks)) -> (B, V, 3)`` can replace it
    through :meth:`BLSM.set_shape_decoder`, e.g. the mesh-convolution decoder of Eq. 11.
    """

    def __init__(self, basis: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("basis", basis, persistent=False)  # (Ks, V, 3)

    @property
    def num_coeffs(self) -> int:
        return int(self.basis.shape[0])

    def forward(self, coeffs: torch.Tensor) -> torch.Tensor:
        return linear_shape(coeffs, self.basis)


class BLSM(nn.Module):
    """Bone-Level Skinned Model: bone scales, 47 joint-limited atoms, blendshapes, LBS.

    Build it with :func:`blsm.load`. Buffers are rebuilt from the model file, so ``.to(device)``
    and ``.double()`` move and convert everything.
    """

    def __init__(self, data: io.ModelData) -> None:
        super().__init__()
        where = str(data.path) if data.path is not None else "model"
        a, meta = data.arrays, data.meta
        self.meta = meta
        self.dof_table: DofTable = parse_dof_table(data.dof_table_yaml, f"{where}:dof_table_yaml")
        self.bone_names: list[str] = list(meta["bone_names"])
        self.parents: list[int] = [int(p) for p in meta["parents"]]
        self.part_names: list[str] = list(meta["part_names"])
        self.keypoint_names: list[str] = list(meta["keypoint_names"])
        self.keypoint_sets: dict[str, list[int]] = {
            k: [self.keypoint_names.index(n) for n in v]
            for k, v in meta.get("keypoint_sets", {}).items()
        }
        try:
            tree_levels(tuple(self.parents))  # validates the bone order once, cached for forward
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from exc
        unknown = {d.joint for d in self.dof_table.dofs} - set(self.bone_names)
        if unknown:
            raise ValueError(f"{where}: DoF table names unknown joints {sorted(unknown)}")

        dofs = self.dof_table.dofs
        n_dof = len(dofs)
        per_joint: list[list[int]] = [[] for _ in self.bone_names]
        for i, d in enumerate(dofs):
            per_joint[self.bone_names.index(d.joint)].append(i)
        width = max(1, max(len(s) for s in per_joint))
        slots = [s + [n_dof] * (width - len(s)) for s in per_joint]
        perm, sign = self.dof_table.mirror_permutation()

        f32 = torch.float32

        def buf(name: str, value: torch.Tensor) -> None:
            self.register_buffer(name, value, persistent=False)

        buf("template", torch.as_tensor(a["template"], dtype=f32))
        buf("faces", torch.as_tensor(a["faces"], dtype=torch.long))
        buf("uvs", torch.as_tensor(a["uvs"], dtype=f32))
        buf("faces_uv", torch.as_tensor(a["faces_uv"], dtype=torch.long))
        buf("weights", torch.as_tensor(a["weights"], dtype=f32))
        buf("heads", torch.as_tensor(a["heads"], dtype=f32))
        buf("frames", torch.as_tensor(a["frames"], dtype=f32))
        buf("bone_mean", torch.as_tensor(a["bone_mean"], dtype=f32))
        buf("bone_basis", torch.as_tensor(a["bone_basis"], dtype=f32))
        buf("bone_correctives", torch.as_tensor(a["bone_correctives"], dtype=f32))
        buf("population_bone", torch.as_tensor(a["population_bone"], dtype=f32))
        buf("population_shape", torch.as_tensor(a["population_shape"], dtype=f32))
        buf("vertex_parts", torch.as_tensor(a["vertex_parts"], dtype=torch.long))
        buf("vertex_bones", torch.as_tensor(a["vertex_bones"], dtype=torch.long))
        buf("vertex_mirror", torch.as_tensor(a["vertex_mirror"], dtype=torch.long))
        buf("keypoint_joint", torch.as_tensor(a["keypoint_joint"], dtype=torch.long))
        buf("keypoint_vertices", torch.as_tensor(a["keypoint_vertices"], dtype=torch.long))
        buf("keypoint_weights", torch.as_tensor(a["keypoint_weights"], dtype=f32))
        buf("parents_t", torch.as_tensor(self.parents, dtype=torch.long))
        chain = torch.zeros(len(self.parents), len(self.parents))
        for j in range(len(self.parents)):
            k = j
            while self.parents[k] >= 0:  # chain[j, k] = 1 for every non-root bone on root -> j
                chain[j, k] = 1.0
                k = self.parents[k]
        buf("chain", chain)
        buf("dof_limits", self.dof_table.limits_tensor().to(f32))
        buf("dof_axis", torch.tensor([d.axis for d in dofs], dtype=torch.long))
        buf("dof_sign", torch.tensor([float(d.axis_sign) for d in dofs], dtype=f32))
        buf("dof_slots", torch.tensor(slots, dtype=torch.long))
        buf("dof_mirror_perm", torch.tensor(perm, dtype=torch.long))
        buf("dof_mirror_sign", torch.tensor([float(s) for s in sign], dtype=f32))
        self.shape_decoder: nn.Module = LinearShapeDecoder(
            torch.as_tensor(a["shape_basis"], dtype=f32)
        )
        if meta.get("shape_decoder") is not None:  # BLSM-spiral (Eq. 11): D(z) and the training codes
            from blsm.spiral.shape import decoder_from_arrays

            decoder, codes = decoder_from_arrays(a, meta["shape_decoder"], where)
            self.set_shape_decoder(decoder.requires_grad_(False))  # a fixed model, like the linear one
            buf("population_shape", codes)

    # ----------------------------------------------------------------------------------------
    # Sizes and names

    @property
    def num_dofs(self) -> int:
        return len(self.dof_table)

    @property
    def dof_names(self) -> list[str]:
        return self.dof_table.names

    @property
    def num_bone_coeffs(self) -> int:
        return int(self.bone_basis.shape[0])

    @property
    def num_shape_coeffs(self) -> int:
        return int(self.shape_decoder.num_coeffs)

    @property
    def num_vertices(self) -> int:
        return int(self.template.shape[0])

    @property
    def num_joints(self) -> int:
        return len(self.bone_names)

    @property
    def dof_mirror(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(perm (47,), sign (47,)): the mirrored pose is ``sign * pose[..., perm]``.

        Valid for angles and for the unconstrained values of Eq. 6 alike.
        """
        return self.dof_mirror_perm, self.dof_mirror_sign

    def mirror_pose(self, pose: torch.Tensor) -> torch.Tensor:
        """Mirror (B, 47) angles or unconstrained values across the sagittal plane."""
        return pose[..., self.dof_mirror_perm] * self.dof_mirror_sign.to(pose.dtype)

    def set_shape_decoder(self, decoder: nn.Module) -> None:
        """Replace ``c_s P_s`` (Eq. 8) by another decoder, e.g. the mesh convolution of Eq. 11."""
        if not hasattr(decoder, "num_coeffs"):
            raise ValueError("decoder must expose num_coeffs")
        self.shape_decoder = decoder

    # ----------------------------------------------------------------------------------------
    # Forward

    def _check(self, name: str, value: torch.Tensor | None, width: int, batch: int | None) -> int | None:
        if value is None:
            return batch
        if not isinstance(value, torch.Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
        if value.dim() != 2 or value.shape[1] != width:
            raise ValueError(f"{name} must be (B, {width}), got {tuple(value.shape)}")
        if value.dtype != self.template.dtype:
            raise ValueError(
                f"{name} must have the model's dtype {self.template.dtype}, got {value.dtype}"
            )
        if value.device != self.template.device:
            raise ValueError(
                f"{name} is on {value.device} but the model is on {self.template.device}"
            )
        if batch is not None and value.shape[0] != batch:
            raise ValueError(f"{name} has batch size {value.shape[0]}, other inputs have {batch}")
        return value.shape[0]

    def forward(
        self,
        pose: torch.Tensor | None = None,
        bone: torch.Tensor | None = None,
        shape: torch.Tensor | None = None,
        global_orient: torch.Tensor | None = None,
        transl: torch.Tensor | None = None,
        angles: torch.Tensor | None = None,
    ) -> BLSMOutput:
        """Pose and shape the model.

        Args:
            pose: (B, 47) unconstrained atom values x; Eq. 6 maps them into the limits.
            bone: (B, num_bone_coeffs) bone coefficients c_b (Eq. 4).
            shape: (B, num_shape_coeffs) shape coefficients c_s (Eq. 8 / decoder input).
            global_orient: (B, 3) axis-angle rotation of the body about its root joint.
            transl: (B, 3) translation in metres, applied after ``global_orient``.
            angles: (B, 47) atom angles in radians, inside the limits; instead of ``pose``.

        Every argument is optional; omitted pose and angles mean the rest pose (all angles 0).

        Returns:
            :class:`BLSMOutput`.

        Raises:
            ValueError: on a wrong shape, dtype or device, on both ``pose`` and ``angles``, or on
                angles outside their limits.
        """
        if pose is not None and angles is not None:
            raise ValueError("give either pose (unconstrained) or angles (radians), not both")
        d = self.num_dofs
        batch = None
        batch = self._check("pose", pose, d, batch)
        batch = self._check("angles", angles, d, batch)
        batch = self._check("bone", bone, self.num_bone_coeffs, batch)
        batch = self._check("shape", shape, self.num_shape_coeffs, batch)
        batch = self._check("global_orient", global_orient, 3, batch)
        batch = self._check("transl", transl, 3, batch)
        batch = 1 if batch is None else batch
        dtype, device = self.template.dtype, self.template.device

        if pose is not None:
            theta = angles_from_unconstrained(pose, self.dof_limits)
        elif angles is not None:
            lo, hi = self.dof_limits[:, 0], self.dof_limits[:, 1]
            bad = ((angles < lo) | (angles > hi)).any(0)
            if bad.any():
                i = int(bad.nonzero()[0])
                raise ValueError(
                    f"angles[:, {i}] ({self.dof_names[i]}) is outside its limits "
                    f"[{float(lo[i]):.4f}, {float(hi[i]):.4f}] rad"
                )
            theta = angles
        else:
            theta = torch.zeros(batch, d, dtype=dtype, device=device)

        if bone is not None:
            b = bone_scales(bone, self.bone_mean, self.bone_basis)  # Eq. 4
        else:
            b = self.bone_mean.expand(batch, -1)
        s = local_scales(b, self.parents_t)  # Eq. 5
        rot = joint_rotations(theta, self.dof_slots, self.dof_axis, self.dof_sign)
        g_rot = None
        if global_orient is not None:
            from kornia.geometry.conversions import axis_angle_to_rotation_matrix

            g_rot = axis_angle_to_rotation_matrix(global_orient)
        linear, offset, joints = forward_kinematics(
            rot, s, self.heads, self.frames, self.parents, g_rot, transl
        )
        shape_offsets = self.shape_decoder(shape) if shape is not None else None
        template = blend_shapes(self.template, bone, self.bone_correctives, shape_offsets)
        template = template.expand(batch, -1, -1)  # Eqs. 1, 7, 8
        vertices = linear_blend_skinning(template, self.weights, linear, offset)  # Eq. 12
        keypoints = self._keypoints(vertices, joints)

        rest = rest_joints(b, self.heads, self.parents_t, self.chain)  # bind pose of this person
        return BLSMOutput(
            vertices=vertices,
            joints=joints,
            keypoints=keypoints,
            angles=theta,
            bone_scales=b,
            template=template,
            rest_joints=rest,
            skinning_transforms=torch.cat([linear, offset[..., None]], dim=-1),
        )

    def _keypoints(self, vertices: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
        surf = (vertices[:, self.keypoint_vertices] * self.keypoint_weights[..., None]).sum(2)
        from_joint = joints[:, self.keypoint_joint.clamp(min=0)]
        is_joint = (self.keypoint_joint >= 0)[None, :, None]
        return torch.where(is_joint, from_joint, surf)

    def extra_repr(self) -> str:
        return (
            f"vertices={self.num_vertices}, faces={int(self.faces.shape[0])}, "
            f"bones={self.num_joints}, dofs={self.num_dofs}, "
            f"bone_coeffs={self.num_bone_coeffs}, shape_coeffs={self.num_shape_coeffs}, "
            f"keypoints={len(self.keypoint_names)}"
        )


def load(path: str | Path | None = None) -> BLSM:
    """Load a BLSM model file (default: the packaged model built from Anny).

    Args:
        path: a ``.npz`` file written by :func:`blsm.io.save_model`, or None for the packaged one.

    Returns:
        A float32 :class:`BLSM` on the CPU; use ``.double()`` / ``.to(device)`` as needed.
    """
    return BLSM(io.read_model(DEFAULT_MODEL if path is None else path))
