"""Crop geometry of the dataset readers: the affine map from image to crop pixels (pixel centres at
integer + 0.5 in both), the matching camera-frame rotation, points and images through it, and the
anti-aliasing prefilter of a crop that shrinks its image.

A crop of side ``s`` source pixels centred at ``c``, rotated by ``r`` degrees (counter-clockwise on
screen) and optionally mirrored, is the map ``A`` of :func:`crop_affine`; the camera frame turns by
``L = M Rz`` (:func:`camera_rotation`), so that ``K_crop = A K L^T`` projects ``L X`` where ``K``
projected ``X``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from kornia.geometry.transform import warp_affine

__all__ = ["camera_rotation", "crop_affine", "crop_shrink", "map_points", "prefilter_for_crop", "warp_to_crop"]


def crop_affine(
    center: Sequence[float], side: float, crop: int, rotation_deg: float = 0.0, flip: bool = False
) -> np.ndarray:
    """The map from original to crop pixel coordinates (both with pixel centres at integer + 0.5).

    Args:
        center: (2,) crop centre in original pixels; it maps to ``(crop / 2, crop / 2)``.
        side: crop side in original pixels.
        crop: output size in pixels.
        rotation_deg: in-plane rotation of the content, counter-clockwise on screen, degrees.
        flip: mirror the crop horizontally (``x -> crop - x``).

    Returns:
        (3, 3) float64 affine matrix ``A``; a point ``p`` maps to ``A [p, 1]``.
    """
    if side <= 0 or crop < 1:
        raise ValueError(f"crop side and size must be positive, got {side}, {crop}")
    out = (crop / side) * camera_rotation(rotation_deg, False)
    out[2] = [0.0, 0.0, 1.0]
    out[:2, 2] = crop / 2 - out[:2, :2] @ np.asarray(center, dtype=np.float64)
    if flip:
        out = np.array([[-1.0, 0.0, crop], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) @ out
    return out


def map_points(points: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """(..., 2) pixel points through a (3, 3) affine (:func:`crop_affine`'s ``A``, or its inverse to go
    from crop back to original pixels): ``A [p, 1]``, without the homogeneous coordinate."""
    return points @ affine[:2, :2].T + affine[:2, 2]


def camera_rotation(rotation_deg: float, flip: bool) -> np.ndarray:
    """``L = M Rz`` (3, 3): the camera-frame map matching :func:`crop_affine`'s rotation and flip."""
    c, s = math.cos(math.radians(rotation_deg)), math.sin(math.radians(rotation_deg))
    return np.diag([-1.0 if flip else 1.0, 1.0, 1.0]) @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def warp_to_crop(image: torch.Tensor, affine: np.ndarray, crop: int, mode: str = "bilinear",
                 antialias: bool = True) -> torch.Tensor:
    """Warp (C, H, W) into (C, crop, crop) with :func:`crop_affine`'s ``A``; zeros outside.

    kornia's ``warp_affine`` (``align_corners=True``) puts pixel centres at integers, so ``A`` is
    conjugated by the half-pixel shift: output pixel ``(u, v)`` samples ``A^-1 (u + .5, v + .5) - .5``.

    With ``antialias`` (bilinear only) a crop that shrinks its source by ``s > 1`` source pixels per
    crop pixel is low-pass filtered first (:func:`prefilter_for_crop`): bilinear sampling alone reads
    4 of every ``s^2`` source pixels, so a person photographed at 800 px and seen at 128 px would
    arrive aliased, a look no rendered training crop has.
    """
    if antialias and mode == "bilinear":
        image, affine = prefilter_for_crop(image, affine, crop)
    half = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    m = np.linalg.inv(half) @ affine @ half
    mt = torch.as_tensor(m[None, :2], dtype=image.dtype)
    return warp_affine(image[None], mt, (crop, crop), mode=mode, align_corners=True)[0]


def crop_shrink(affine: np.ndarray) -> float:
    """Source pixels per crop pixel of a similarity ``A`` (:func:`crop_affine`): ``|det A|^-1/2``."""
    return float(abs(np.linalg.det(np.asarray(affine, np.float64)[:2, :2])) ** -0.5)


def prefilter_for_crop(image: torch.Tensor, affine: np.ndarray, crop: int) -> tuple[torch.Tensor, np.ndarray]:
    """The source region a crop reads, low-pass filtered for its shrink ``s`` (:func:`crop_shrink`),
    and the affine from that region's pixels to the crop's. Identity where ``s <= 1``.

    The region is the crop's footprint plus a margin, cut from the image (what lies outside the
    image stays outside: the warp fills it with zeros). Then, as an image pyramid does, it is
    averaged over ``k x k`` blocks for the integer part ``k = floor(s)`` (area resampling; the
    block ``i`` covers source pixels ``[k i, k i + k)``, centre ``k (i + 1/2)``, so the affine gains
    ``diag(k, k, 1)``), and the remaining shrink ``r = s / k`` in ``[1, 2)`` is covered by a
    Gaussian of ``sigma = (r - 1) / 2`` (scikit-image's ``resize`` anti-aliasing rule).

    Args:
        image: (C, H, W) float.
        affine: (3, 3) source -> crop pixel coordinates (pixel centres at integer + 0.5).
        crop: crop side in pixels.
    """
    from kornia.filters import gaussian_blur2d

    affine = np.asarray(affine, np.float64)
    s = crop_shrink(affine)
    if not s > 1.0 + 1e-6:
        return image, affine
    h, w = image.shape[-2:]
    inv = np.linalg.inv(affine)
    corners = np.array([[0, 0, 1], [crop, 0, 1], [0, crop, 1], [crop, crop, 1]], np.float64) @ inv.T
    margin = 3.0 * s + 2.0
    k = int(math.floor(s))
    # the region starts on the block grid of the whole image, so two crops of one image at one
    # shrink see the same blocks wherever they lie (the cache's crop and the dataset's agree)
    x0 = int(np.clip(np.floor(corners[:, 0].min() - margin), 0, w)) // k * k
    x1 = int(np.clip(np.ceil(corners[:, 0].max() + margin), 0, w))
    y0 = int(np.clip(np.floor(corners[:, 1].min() - margin), 0, h)) // k * k
    y1 = int(np.clip(np.ceil(corners[:, 1].max() + margin), 0, h))
    if x1 - x0 < 1 or y1 - y0 < 1:  # the crop sees none of the image: zeros either way
        return image, affine
    region = image[..., y0:y1, x0:x1]
    shift = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])
    affine = affine @ shift
    if k >= 2:
        rh, rw = region.shape[-2:]
        ph, pw = -rh % k, -rw % k  # the last block is filled by repeating the edge (under one block)
        if ph or pw:
            region = torch.nn.functional.pad(region[None], (0, pw, 0, ph), mode="replicate")[0]
        region = torch.nn.functional.avg_pool2d(region[None], k)[0]
        affine = affine @ np.diag([float(k), float(k), 1.0])
        s = s / k
    sigma = (s - 1.0) / 2.0
    if sigma > 0.05:
        size = 2 * int(math.ceil(3.0 * sigma)) + 1
        region = gaussian_blur2d(region[None], (size, size), (sigma, sigma), border_type="replicate")[0]
    return region, affine
