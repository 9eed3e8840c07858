"""BLSM: the Bone-Level Skinned Model of the human mesh (Wang et al., ECCV 2020).

    import blsm
    model = blsm.load()
    out = model(pose=x, bone=cb, shape=cs, global_orient=r, transl=t)

Metres, radians, Y up, the body faces +Z at rest (+X is the body's left).
"""

from __future__ import annotations

from blsm.model import BLSM, BLSMOutput, LinearShapeDecoder, load

__version__ = "0.1.0"

__all__ = ["BLSM", "BLSMOutput", "LinearShapeDecoder", "load", "__version__"]
