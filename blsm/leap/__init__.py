"""LEAP (Mihajlovic et al., CVPR 2021) on BLSM's bones: a learned articulated occupancy
(:mod:`blsm.leap.model`). The exact occupancy it learns is :mod:`blsm.occupancy`'s."""

from blsm.leap.model import Leap, LeapConfig, blend_forward, blend_inverse

__all__ = ["Leap", "LeapConfig", "blend_forward", "blend_inverse"]
