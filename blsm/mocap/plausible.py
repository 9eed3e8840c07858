"""Anatomical plausibility of a pose: feet pointing backwards, limbs through the torso.

The pose prior (:mod:`blsm.mocap.prior`) is a Gaussian mixture over the 47 unconstrained atom values;
every atom stays inside its joint limit (Eq. 6 of paper 000), but a draw may combine atoms that no
person holds together: a hip rotated inwards with an abducted ankle turns the foot backwards, a
flexed shoulder with a flexed elbow pushes the hand into the chest. Per-atom limits cannot exclude
such combinations; this module tests for them on the model's mean body (bone and shape
coefficients 0, no global orientation), so the test depends on the pose only.

**Foot backwards.** The pelvis' forward axis ``f`` is its skinning rotation applied to the rest
forward +Z (the body faces +Z at rest). A foot points backwards when its heel-to-toe vector
``toe_tip - heel`` has a negative component along ``f`` -- the toes behind the heel relative to the
pelvis -- *with the leg straightened*: the sagittal atoms (``hip.flex``, ``knee.flex``,
``ankle.plantarflex``) are set to 0 first. Those atoms swing the foot in the leg's own plane: a
runner's heel kicked up behind, a walker's foot at toe-off or a kneeling shin puts the toes behind
the heel in real poses (about 3.5 % of the feet of the 45 training CMU clips, as often as in prior
draws), while a foot that still points backwards once the leg is straight is turned beyond 90
degrees by the twist atoms (hip rotation and abduction, ankle abduction and inversion). The
packaged model's limits stop that twist short of 90 degrees (``tests/blsm/test_plausible.py``
tries every corner), so with it the test guards models with wider limits. ``blsm mocap
plausibility`` counts both measures.

**Limb through the torso.** The torso is the mesh part ``torso``; its vertices are grouped by the
torso bone they follow (``pelvis``, ``spine_01..03``) and each group's convex hull is taken in the
rest pose, shrunk by ``margin`` (3 cm). Limb points -- elbows, wrists, hand tips, knees, ankles, toe
tips and the midpoints of upper arms, forearms, thighs and shins -- are carried into each torso
bone's rest frame by the inverse of that bone's skinning transform (Eq. 12, ``A_j``), and a limb
passes through the torso when one of its points lies inside a hull. Points of a limb only touching
the body surface stay outside the shrunk hulls.

:func:`plausible` returns one flag per pose; :class:`PoseChecker` gives the details.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import ConvexHull

from blsm.joint_limits import angles_from_unconstrained
from blsm.kinematics import forward_kinematics, joint_rotations, local_scales
from blsm.lbs import linear_blend_skinning

SAGITTAL = ("hip_l.flex", "knee_l.flex", "ankle_l.plantarflex", "hip_r.flex", "knee_r.flex", "ankle_r.plantarflex")
TORSO_BONES = ("pelvis", "spine_01", "spine_02", "spine_03")
LIMB_POINTS = (
    "elbow_l", "wrist_l", "hand_tip_l", "elbow_r", "wrist_r", "hand_tip_r",
    "knee_l", "ankle_l", "toe_tip_l", "knee_r", "ankle_r", "toe_tip_r",
)  # fmt: skip
LIMB_MIDPOINTS = (
    ("shoulder_l", "elbow_l"), ("elbow_l", "wrist_l"), ("shoulder_r", "elbow_r"), ("elbow_r", "wrist_r"),
    ("hip_l", "knee_l"), ("knee_l", "ankle_l"), ("hip_r", "knee_r"), ("knee_r", "ankle_r"),
)  # fmt: skip


@dataclass(frozen=True)
class PoseCheck:
    """Per-pose results of :meth:`PoseChecker.check` (numpy arrays over the batch).

    Attributes:
        foot_forward: (B, 2) heel-to-toe component along the pelvis' forward axis (metres), left and
            right foot; negative means the foot points backwards.
        foot_backwards: (B, 2) bool, ``foot_forward < 0``.
        limb_in_torso: (B,) bool, a limb point lies inside the shrunk torso.
        toes_behind_heel: (B, 2) bool, the toes behind the heel along the pelvis' forward axis with
            the legs as posed (not straightened): information, not a test.
        plausible: (B,) bool, neither a backward foot nor a limb through the torso.
    """

    foot_forward: np.ndarray
    foot_backwards: np.ndarray
    limb_in_torso: np.ndarray
    toes_behind_heel: np.ndarray

    @property
    def plausible(self) -> np.ndarray:
        return ~(self.foot_backwards.any(1) | self.limb_in_torso)


class PoseChecker:
    """Tests poses of a BLSM model for backward feet and limbs through the torso (module docstring).

    Args:
        model: the BLSM model (:func:`blsm.load`).
        margin: how far inside the torso's surface (metres) a limb point must be to count.
    """

    def __init__(self, model, margin: float = 0.03) -> None:
        self.model = model
        self.margin = float(margin)
        names, kp = list(model.bone_names), list(model.keypoint_names)
        self._bone = {n: names.index(n) for n in names}
        self._kp = {n: kp.index(n) for n in kp}
        missing = [n for n in (*LIMB_POINTS, "heel_l", "heel_r") if n not in kp]
        if missing:
            raise ValueError(f"the model has no keypoints {missing}")
        with torch.no_grad():
            rest = model(pose=torch.zeros(1, model.num_dofs, dtype=model.weights.dtype))
        template = rest.template[0].double().numpy()
        parts = model.vertex_parts.numpy()
        bones = model.vertex_bones.numpy()
        torso = list(model.part_names).index("torso")
        dofs = list(model.dof_names)
        self._sagittal = [dofs.index(d) for d in SAGITTAL if d in dofs]
        self._hulls: list[tuple[int, np.ndarray]] = []
        for b in TORSO_BONES:
            j = self._bone[b]
            pts = template[(parts == torso) & (bones == j)]
            eq = ConvexHull(pts).equations  # (F, 4): n . p + d <= 0 inside, n unit
            self._hulls.append((j, eq))
        # The checks read joints and a few surface keypoints only: forward kinematics and LBS of
        # those keypoints' vertices replace a forward pass of the whole mesh (no pose-dependent
        # blendshape changes the mean body's template, so the result is the same).
        self._need = sorted({self._kp[n] for n in (*LIMB_POINTS, "heel_l", "heel_r")})
        kv = model.keypoint_vertices[self._need]
        sub, local = torch.unique(kv.reshape(-1), return_inverse=True)
        self._sub_template = rest.template[0, sub].double()
        self._sub_weights = model.weights[sub].double()
        self._kp_local = local.reshape(kv.shape)
        self._kp_weights = model.keypoint_weights[self._need].double()
        self._kp_joint = model.keypoint_joint[self._need]
        self._scales = local_scales(model.bone_mean.double()[None], model.parents_t)

    def _skeleton(self, angles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The mean body in poses ``angles`` (B, 47): keypoints (B, K, 3) with only the checked
        ones filled, joints (B, J, 3) and skinning transforms (B, J, 3, 4), as ``model(angles=...)``
        gives them."""
        m = self.model
        angles = angles.double()
        rot = joint_rotations(angles, m.dof_slots, m.dof_axis, m.dof_sign)
        linear, offset, joints = forward_kinematics(
            rot, self._scales.expand(len(angles), -1), m.heads.double(), m.frames.double(), m.parents, None, None
        )
        verts = linear_blend_skinning(self._sub_template.expand(len(angles), -1, -1), self._sub_weights, linear, offset)
        surf = (verts[:, self._kp_local] * self._kp_weights[..., None]).sum(2)
        at_joint = (self._kp_joint >= 0)[None, :, None]
        kp = torch.zeros(len(angles), len(m.keypoint_names), 3, dtype=torch.float64)
        kp[:, self._need] = torch.where(at_joint, joints[:, self._kp_joint.clamp(min=0)], surf)
        return kp, joints, torch.cat([linear, offset[..., None]], dim=-1)

    def check(self, pose: torch.Tensor) -> PoseCheck:
        """Check unconstrained poses ``pose`` (B, 47) on the mean body."""
        m = self.model
        with torch.no_grad():
            angles = angles_from_unconstrained(pose.to(m.weights.dtype), m.dof_limits.to(m.weights.dtype))
            kp, joints, A = self._skeleton(angles)  # A: (B, J, 3, 4), rest -> posed
            straight = angles.clone()
            straight[:, self._sagittal] = 0.0
            fk, _, A_straight = self._skeleton(straight)
        b, k = self._bone, self._kp

        # The pelvis' forward axis: its skinning rotation applied to the rest forward +Z.
        forward = A_straight[:, b["pelvis"], :, 2]
        feet = torch.stack(
            [fk[:, k["toe_tip_l"]] - fk[:, k["heel_l"]], fk[:, k["toe_tip_r"]] - fk[:, k["heel_r"]]], dim=1
        )  # (B, 2, 3)
        foot_forward = (feet * forward[:, None]).sum(-1)
        posed = torch.stack(
            [kp[:, k["toe_tip_l"]] - kp[:, k["heel_l"]], kp[:, k["toe_tip_r"]] - kp[:, k["heel_r"]]], dim=1
        )
        posed_forward = (posed * A[:, b["pelvis"], None, :, 2]).sum(-1)

        pts = [kp[:, k[n]] for n in LIMB_POINTS]
        pts += [0.5 * (joints[:, b[p]] + joints[:, b[q]]) for p, q in LIMB_MIDPOINTS]
        P = torch.stack(pts, dim=1)  # (B, N, 3) posed
        depth = torch.full(P.shape[:2], -1.0, dtype=torch.float64)  # how far inside (m), < 0 outside
        for j, eq in self._hulls:
            R, t = A[:, j, :, :3], A[:, j, :, 3]
            rest = torch.einsum("bji,bnj->bni", R, P - t[:, None])  # R^T (p - t)
            E = torch.as_tensor(eq)
            dist = rest @ E[:, :3].T + E[:, 3]  # (B, N, F), <= 0 inside each face's half-space
            depth = torch.maximum(depth, -dist.max(-1).values)
        inside = depth >= self.margin
        fwd = foot_forward.numpy()
        return PoseCheck(foot_forward=fwd, foot_backwards=fwd < 0, limb_in_torso=inside.any(1).numpy(),
                         toes_behind_heel=posed_forward.numpy() < 0)


def plausible(checker: PoseChecker, pose: torch.Tensor) -> np.ndarray:
    """(B,) bool: the poses that have no backward foot and no limb through the torso."""
    return checker.check(pose).plausible
