"""Motion capture: BVH import, retargeting onto the 47 BLSM atoms, motion library, pose prior."""

from blsm.mocap.bvh import BvhError, BvhMotion, read_bvh, resample
from blsm.mocap.library import MotionClip, list_clips, load_clip, save_clip

__all__ = [
    "BvhError",
    "BvhMotion",
    "MotionClip",
    "list_clips",
    "load_clip",
    "read_bvh",
    "resample",
    "save_clip",
]
