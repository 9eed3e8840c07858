"""sRGB transfer functions (IEC 61966-2-1).

Images on disk and colours given by users are sRGB-encoded; renderers work in linear RGB.  Both
functions clip to ``[0, 1]`` first and keep the dtype of float input (integer input is converted
to float64 without rescaling: divide uint8 by 255 first).
"""

from __future__ import annotations

import numpy as np

__all__ = ["linear_to_srgb", "srgb_to_linear"]


def _unit_float(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c)
    return np.clip(c if c.dtype.kind == "f" else c.astype(np.float64), 0.0, 1.0)


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """Decodes sRGB values to linear RGB.

    Args:
        c: Array of any shape of sRGB-encoded values in [0, 1] (clipped to it).

    Returns:
        Linear values in [0, 1], same shape; float input keeps its dtype, other input is float64.
    """
    c = _unit_float(c)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(c.dtype, copy=False)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    """Encodes linear RGB values as sRGB.

    Args:
        c: Array of any shape of linear values in [0, 1] (clipped to it).

    Returns:
        sRGB-encoded values in [0, 1], same shape; float input keeps its dtype, other input is
        float64.
    """
    c = _unit_float(c)
    encoded = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)
    return encoded.astype(c.dtype, copy=False)
