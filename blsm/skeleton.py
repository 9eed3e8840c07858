"""The BLSM bone tree and its bind frames (paper 000 Sec. 3.1; thesis Sec. 5.3.1).

A bone is named after the joint at its head (``knee_l`` is the shin: its head is the left knee).
Every bone has a bind frame ``Q`` (3, 3), whose columns are the frame's x, y, z axes in world
coordinates, and a head position ``h`` (3,) in the bind pose. In terms of the paper's Eq. 3 the bind
rotation and offset of bone j relative to its parent p are ``R^t_j = Q_p^T Q_j`` and
``O^t_j = Q_p^T (h_j - h_p)``.

Frames follow one rule so that the pose atoms of ``dofs.yaml`` mean the same on both sides:
y runs along the bone (head to tail); for the trunk, head and legs x is the world +X (the body's left)
made orthogonal to y; for clavicles and arms z is the world +Z (the body's front) made orthogonal to
y and x = y cross z. Under the mirror x -> -x such frames map onto their partner's with x negated,
so rotations about x keep their sign and rotations about y and z flip (see ``dofs.yaml``).
"""

from __future__ import annotations

import numpy as np

# (name, parent, frame rule, six-part label). Order is topological: parents come first.
BONES: tuple[tuple[str, str | None, str, str], ...] = (
    ("pelvis", None, "lateral", "torso"),
    ("spine_01", "pelvis", "lateral", "torso"),
    ("spine_02", "spine_01", "lateral", "torso"),
    ("spine_03", "spine_02", "lateral", "torso"),
    ("neck", "spine_03", "lateral", "head"),
    ("head", "neck", "lateral", "head"),
    ("clavicle_l", "spine_03", "frontal", "torso"),
    ("shoulder_l", "clavicle_l", "frontal", "left_arm"),
    ("elbow_l", "shoulder_l", "frontal", "left_arm"),
    ("wrist_l", "elbow_l", "frontal", "left_arm"),
    ("clavicle_r", "spine_03", "frontal", "torso"),
    ("shoulder_r", "clavicle_r", "frontal", "right_arm"),
    ("elbow_r", "shoulder_r", "frontal", "right_arm"),
    ("wrist_r", "elbow_r", "frontal", "right_arm"),
    ("hip_l", "pelvis", "lateral", "left_leg"),
    ("knee_l", "hip_l", "lateral", "left_leg"),
    ("ankle_l", "knee_l", "lateral", "left_leg"),
    ("hip_r", "pelvis", "lateral", "right_leg"),
    ("knee_r", "hip_r", "lateral", "right_leg"),
    ("ankle_r", "knee_r", "lateral", "right_leg"),
)

BONE_NAMES: tuple[str, ...] = tuple(b[0] for b in BONES)
BONE_PARENTS: tuple[int, ...] = tuple(
    -1 if b[1] is None else BONE_NAMES.index(b[1]) for b in BONES
)
BONE_FRAME_RULES: tuple[str, ...] = tuple(b[2] for b in BONES)

# The thesis' six parts (Sec. 6.5, LSP part segmentation): left/right are the person's own.
PART_NAMES: tuple[str, ...] = ("head", "torso", "left_arm", "right_arm", "left_leg", "right_leg")
BONE_PARTS: tuple[int, ...] = tuple(PART_NAMES.index(b[3]) for b in BONES)

# The tail of a bone ends its length; for bones with several children the first listed one.
# Leaves end at a surface point chosen by the model builder (head top, middle fingertip, toe tip).
LEAF_TIPS: dict[str, str] = {
    "head": "head_top",
    "wrist_l": "hand_tip_l",
    "wrist_r": "hand_tip_r",
    "ankle_l": "toe_tip_l",
    "ankle_r": "toe_tip_r",
}
"""The surface keypoint that ends each leaf bone (its tail)."""

PRIMARY_CHILD: dict[str, str] = {
    "pelvis": "spine_01",
    "spine_01": "spine_02",
    "spine_02": "spine_03",
    "spine_03": "neck",
    "neck": "head",
    "clavicle_l": "shoulder_l",
    "shoulder_l": "elbow_l",
    "elbow_l": "wrist_l",
    "clavicle_r": "shoulder_r",
    "shoulder_r": "elbow_r",
    "elbow_r": "wrist_r",
    "hip_l": "knee_l",
    "knee_l": "ankle_l",
    "hip_r": "knee_r",
    "knee_r": "ankle_r",
}


def mirror_name(name: str) -> str:
    """Left/right counterpart of a bone or keypoint name (``_l`` <-> ``_r``, ``left`` <-> ``right``)."""
    for a, b in (("_l", "_r"), ("_r", "_l")):
        if name.endswith(a):
            return name[: -len(a)] + b
    for a, b in (("left_", "right_"), ("right_", "left_")):
        if name.startswith(a):
            return b + name[len(a) :]
    return name


def bind_frames(
    heads: np.ndarray, tails: np.ndarray, rules: tuple[str, ...] = BONE_FRAME_RULES
) -> np.ndarray:
    """Construct the bind frames of all bones from their heads and tails.

    Args:
        heads: (J, 3) bone head positions in metres.
        tails: (J, 3) bone tail positions in metres.
        rules: per bone, ``"lateral"`` (x from world +X) or ``"frontal"`` (z from world +Z).

    Returns:
        (J, 3, 3) rotation matrices whose columns are the x, y, z axes of each frame.
    """
    frames = np.zeros((len(heads), 3, 3))
    for j, (h, t, rule) in enumerate(zip(heads, tails, rules)):
        y = t - h
        y = y / np.linalg.norm(y)
        if rule == "lateral":
            x = np.array([1.0, 0.0, 0.0]) - y[0] * y
            x /= np.linalg.norm(x)
            z = np.cross(x, y)
        elif rule == "frontal":
            z = np.array([0.0, 0.0, 1.0]) - y[2] * y
            z /= np.linalg.norm(z)
            x = np.cross(y, z)
        else:
            raise ValueError(f"unknown frame rule {rule!r} for bone {j}")
        frames[j] = np.stack([x, y, z], axis=1)
    return frames
