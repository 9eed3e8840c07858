"""Which pixel centres lie inside 2D triangles: shared by texture baking and label validation.

:func:`rasterise` works in pixel units; :func:`rasterise_uv` finds the texels of a square texture
inside UV triangles (texture painting, scan baking and the texture transfer of the ``blsm``
pipeline).
"""

from __future__ import annotations

import numpy as np


def rasterise(
    tri: np.ndarray, width: int, height: int, eps: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixel centres inside triangles, with the face and barycentric coordinates there.

    Args:
        tri: (F, 3, 2) triangle corners in pixel units, measured so that pixel ``(x, y)`` has its
            centre at ``(x, y)`` (subtract 0.5 from OpenCV image coordinates). Either winding.
        width, height: the image; pixels outside it are never returned.
        eps: tolerance of the inside test on each barycentric coordinate (0: exact).

    Returns:
        ``pixel`` (N,) flat indices ``y * width + x``, one per covered pixel; ``face`` (N,) the
        triangle covering it (the last one listed where triangles overlap); ``bary`` (N, 3) its
        barycentric coordinates for the three corners. Degenerate triangles, and triangles with a
        non-finite corner, cover nothing.
    """
    tri = np.asarray(tri, dtype=np.float64)
    finite = np.isfinite(tri).all(axis=(1, 2))
    tri = np.where(finite[:, None, None], tri, 0.0)
    size = np.array([width - 1, height - 1])
    lo = np.clip(np.ceil(tri.min(1)), 0, size).astype(np.int64)
    hi = np.clip(np.floor(tri.max(1)), 0, size).astype(np.int64)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    nx, ny = np.maximum(hi - lo + 1, 0).T
    n = np.where((np.abs(det) > 1e-12) & finite, nx * ny, 0)
    with np.errstate(divide="ignore", invalid="ignore"):  # b1, b2 = coef @ (cx, cy) + off
        coef = np.stack([e2[:, 1], -e2[:, 0], -e1[:, 1], e1[:, 0]], 1) / det[:, None]
        off = -(coef.reshape(-1, 2, 2) @ tri[:, 0, :, None])[..., 0]
    fid = np.repeat(np.arange(len(tri)), n)  # one candidate per pixel of each face's bounding box
    k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
    w = np.take(nx, fid)
    cx, cy = np.take(lo[:, 0], fid) + k % w, np.take(lo[:, 1], fid) + k // w
    c, o = np.take(coef, fid, axis=0), np.take(off, fid, axis=0)
    b1 = c[:, 0] * cx + c[:, 1] * cy + o[:, 0]
    b2 = c[:, 2] * cx + c[:, 3] * cy + o[:, 1]
    inside = np.flatnonzero((b1 >= -eps) & (b2 >= -eps) & (b1 + b2 <= 1 + eps))
    where = np.full(width * height, -1, np.int64)
    where[cy[inside] * width + cx[inside]] = inside
    pixel = np.flatnonzero(where >= 0)
    sel = where[pixel]
    b1, b2 = b1[sel], b2[sel]
    return pixel, fid[sel], np.stack([1 - b1 - b2, b1, b2], 1)


def uv_triangles(uv: np.ndarray, faces_uv: np.ndarray, size: int) -> np.ndarray:
    """(F, 3, 2) UV triangles in the texel units of :func:`rasterise` for a ``size x size`` texture:
    texel ``(x, y)`` has its centre at ``(x, y)``; ``uv`` (U, 2) is v up (row 0 of the image is
    v = 1)."""
    return np.stack([uv[faces_uv, 0] * size - 0.5, (1 - uv[faces_uv, 1]) * size - 0.5], -1)


def rasterise_uv(uv: np.ndarray, faces_uv: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The texel centres of a ``size x size`` texture inside UV triangles (later faces win).

    Args:
        uv: (U, 2) texture coordinates, v up (row 0 of the image is v = 1).
        faces_uv: (F, 3) indices into ``uv``.
        size: the texture's width and height, texels.

    Returns:
        ``texels`` (N,) flat indices into the ``size x size`` image, ``face`` (N,) and the
        barycentric coordinates there, ``bary`` (N, 3). A texel centre on a triangle's edge (within
        1e-9) is inside it.
    """
    return rasterise(uv_triangles(uv, faces_uv, size), size, size, eps=1e-9)
