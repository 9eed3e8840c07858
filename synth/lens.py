"""Depth of field of a thin lens focused on the people, applied to the backdrop.

A thin lens of focal length ``f`` and aperture diameter ``A = f / N`` (``N`` the f-number) focused
at distance ``s`` images a point at depth ``z`` as a disc -- the circle of confusion -- of diameter
``A f |z - s| / (z (s - f))`` on the sensor, centred on the point's pinhole projection (the ray
through the lens centre is undeviated). In pixels, with ``f_px`` the focal length in pixels and
``s >> f``::

    c(z) = A * f_px * |1/s - 1/z|        (A in metres; c(inf) = A f_px / s)

The generator focuses on the people (``s`` is the depth of their centre in the camera frame). Their
own depth range is small against ``s`` (0.5 m at 5 m gives 0.06 px with a 50 mm f/2.8 lens on a
192 px image), so they are rendered sharp by the pinhole, and the blur is the backdrop's: the
environment at infinity and the ground plane at its depth per pixel
(:func:`synth.ground.ground_points`). The backdrop holds no people, so blurring it and then
compositing the sharp people over it is the thin lens' image up to the partial occlusion at the
people's outline (a real lens lets the blurred backdrop show slightly through the edge of an
in-focus foreground; here the edge is the pinhole's).

**Labels stay exact**: the people's geometry, masks, parts, depth and keypoints are the pinhole's,
which is also where a thin lens puts every point of the people in focus; only backdrop pixels change.

The variable blur is a gather over a few disc kernels: the backdrop is convolved with discs of
diameters ``LEVELS`` and each pixel takes the linear interpolation between the two levels around
its own ``c`` (a standard layered approximation; exact for a constant ``c``).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import convolve

LEVELS = (0.0, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0)  # disc diameters, pixels
MAX_COC = LEVELS[-1]


def circle_of_confusion(depth: np.ndarray, focus: float, f_px: float, aperture_m: float) -> np.ndarray:
    """Diameter in pixels of the blur of points at ``depth`` (metres along the optical axis; inf
    for the environment) for a lens focused at ``focus`` metres with aperture diameter
    ``aperture_m`` and focal length ``f_px`` pixels, capped at :data:`MAX_COC`."""
    inv = np.where(np.isfinite(depth), 1.0 / np.maximum(depth, 1e-6), 0.0)
    return np.minimum(aperture_m * f_px * np.abs(1.0 / focus - inv), MAX_COC)


def disc_kernel(diameter: float) -> np.ndarray:
    """A normalised disc of ``diameter`` pixels, anti-aliased by 4 x 4 supersampling (1 x 1 for 0)."""
    if diameter <= 1e-6:
        return np.ones((1, 1))
    r = diameter / 2.0
    n = int(np.ceil(r)) * 2 + 1
    sub = (np.arange(n * 4) + 0.5) / 4.0 - n / 2.0
    x, y = np.meshgrid(sub, sub)
    inside = (x * x + y * y <= r * r).astype(np.float64)
    k = inside.reshape(n, 4, n, 4).mean(axis=(1, 3))
    return k / k.sum()


def defocus(image: np.ndarray, coc: np.ndarray) -> np.ndarray:
    """Blur ``image`` (H, W, C) by the per-pixel circle of confusion ``coc`` (H, W), pixels."""
    coc = np.clip(coc, 0.0, MAX_COC)
    top = float(coc.max())
    levels = [d for d in LEVELS if d <= top] + [d for d in LEVELS if d > top][:1]
    if len(levels) == 1:
        return image.copy()
    stack = []
    for d in levels:
        k = disc_kernel(d)
        stack.append(np.stack([convolve(image[..., c], k, mode="nearest") for c in range(image.shape[-1])], -1))
    lv = np.asarray(levels)
    hi = np.clip(np.searchsorted(lv, coc, side="left"), 1, len(lv) - 1)
    lo = hi - 1
    t = np.clip((coc - lv[lo]) / (lv[hi] - lv[lo]), 0.0, 1.0)[..., None]
    s = np.stack(stack)  # (L, H, W, C)
    rows, cols = np.indices(coc.shape)
    return ((1.0 - t) * s[lo, rows, cols] + t * s[hi, rows, cols]).astype(image.dtype)
