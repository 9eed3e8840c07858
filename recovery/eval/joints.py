"""The evaluation joint set, built from BLSM keypoints (one place; everything indexes through it).

17 joints in the layout of Human3.6M's 17-joint skeleton (pelvis, legs, spine, neck, head, head
top, arms), taken from the BLSM skeleton's joints (bone heads) and its ``head_top`` keypoint:

========== =============================================
pelvis     the root joint
hip/knee/ankle_l, _r   leg joints (person's own left and right)
spine_02   mid spine (H3.6M "spine")
neck       neck joint (H3.6M "thorax" lies between the shoulders; BLSM's neck is the nearest joint)
head       head joint (H3.6M "neck/nose" level)
head_top   top of the head (a surface keypoint)
shoulder/elbow/wrist_l, _r  arm joints
========== =============================================

MPJPE is computed after aligning the pelvis, PA-MPJPE after a similarity Procrustes alignment
over these 17 joints.
"""

from __future__ import annotations

from collections.abc import Sequence

EVAL_JOINTS: tuple[str, ...] = (
    "pelvis", "hip_r", "knee_r", "ankle_r", "hip_l", "knee_l", "ankle_l", "spine_02", "neck", "head",
    "head_top", "shoulder_l", "elbow_l", "wrist_l", "shoulder_r", "elbow_r", "wrist_r",
)
PELVIS = 0  # index of "pelvis" in EVAL_JOINTS


def indices(names: Sequence[str], wanted: Sequence[str] = EVAL_JOINTS) -> list[int]:
    """Indices of ``wanted`` in ``names`` (a ValueError lists the missing ones)."""
    missing = [n for n in wanted if n not in names]
    if missing:
        raise ValueError(f"keypoints {missing} are missing (have {list(names)})")
    return [list(names).index(n) for n in wanted]
