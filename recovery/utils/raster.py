"""An exact z-buffer rasteriser for face-index, depth and label maps (numpy, vectorised, CPU).

Conventions: camera-frame vertices in metres, OpenCV camera (x right, y down, z forward),
intrinsics ``K`` mapping a point to image coordinates ``(u, v) = (K X)[:2] / z`` in pixels, and
pixel ``(x, y)`` covering ``[x, x + 1) x [y, y + 1)`` with its centre at ``(x + 0.5, y + 0.5)``.
A pixel is covered by a triangle when its centre is (inclusive of the edges, up to a relative
tolerance); it takes the covering triangle whose depth there is smallest.

Depth is interpolated perspective-correctly: ``1 / z`` is affine in image coordinates for a
planar triangle, so ``z = 1 / sum_i b_i / z_i`` with the screen-space barycentric coordinates
``b_i`` is the exact camera z of the surface point seen through the pixel centre.

Why not :func:`synth.raster.rasterise` (pixel coverage and barycentrics): it resolves overlaps inside
itself (the last face listed wins) and returns one face per pixel, while a z-buffer needs every
covering face's depth at the pixel; its bounding boxes also lack the 1e-9 px margin this test's
tolerance relies on, so a pixel centre on a box's edge would be lost.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, DTypeLike

# Candidate (face, pixel) pairs processed at once; bounds memory for meshes with huge faces.
_CHUNK = 1 << 22


def _as_array(x: ArrayLike, name: str, dtype: DTypeLike = None) -> np.ndarray:
    if hasattr(x, "detach"):  # a torch tensor, without importing torch here
        x = x.detach().cpu().numpy()
    try:
        return np.asarray(x, dtype=dtype)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} must be array-like, got {type(x).__name__}") from err


def _check_inputs(
    vertices_cam: ArrayLike, faces: ArrayLike, K: ArrayLike, width: int, height: int
) -> tuple[np.ndarray, ...]:
    verts = _as_array(vertices_cam, "vertices_cam", np.float64)
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ValueError(f"vertices_cam must be (V, 3) camera-frame points, got {verts.shape}")
    tri = _as_array(faces, "faces")
    if tri.ndim != 2 or tri.shape[1] != 3 or not (np.issubdtype(tri.dtype, np.integer) or tri.size == 0):
        raise ValueError(f"faces must be an integer (F, 3) array, got {tri.dtype} {tri.shape}")
    tri = tri.astype(np.int64)
    if tri.size and (tri.min() < 0 or tri.max() >= len(verts)):
        raise ValueError(f"faces index vertices outside [0, {len(verts)}): [{tri.min()}, {tri.max()}]")
    k = _as_array(K, "K", np.float64)
    if k.shape != (3, 3) or not np.isfinite(k).all():
        raise ValueError(f"K must be a finite (3, 3) intrinsic matrix, got shape {k.shape}")
    if not np.allclose(k[2], [0.0, 0.0, 1.0]):
        raise ValueError(f"K's last row must be [0, 0, 1] (a pinhole camera), got {k[2].tolist()}")
    _check_size(width, height)
    return verts, tri, k


def _check_size(width: int, height: int) -> None:
    for name, n in (("width", width), ("height", height)):
        if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
            raise ValueError(f"{name} must be a positive int of pixels, got {n!r}")


def rasterize(
    vertices_cam: ArrayLike,
    faces: ArrayLike,
    K: ArrayLike,
    width: int,
    height: int,
    near: float = 1e-3,
    eps: float = 1e-9,
) -> tuple[np.ndarray, np.ndarray]:
    """The nearest face and its depth at every pixel centre (z-buffer, no anti-aliasing).

    Args:
        vertices_cam: (V, 3) vertices in the camera frame, metres (OpenCV: z forward). numpy or a
            CPU / GPU torch tensor.
        faces: (F, 3) integer vertex indices, either winding (no back-face culling).
        K: (3, 3) intrinsics in pixels, last row [0, 0, 1].
        width, height: image size W, H in pixels.
        near: faces with any vertex at ``z <= near`` metres are dropped whole (no clipping).
        eps: tolerance of the inside test in barycentric units, so that a pixel centre on an edge
            shared by two faces is not lost to rounding; 0 for the exact closed test.

    Returns:
        ``face_index`` (H, W) int64, the covering face with the smallest depth (the lowest index
        among equal depths), -1 where no face covers the pixel centre; ``depth`` (H, W) float64,
        its camera z in metres at the pixel centre (perspective-correct), ``inf`` on background.
        Degenerate (zero screen area) faces and faces with a non-finite vertex cover nothing.

    Raises:
        ValueError: on bad shapes, out-of-range face indices, a non-pinhole K or a bad image size.
    """
    verts, tri, k = _check_inputs(vertices_cam, faces, K, width, height)
    best_depth = np.full(height * width, np.inf)
    best_face = np.full(height * width, -1, np.int64)
    if len(tri) == 0:
        return best_face.reshape(height, width), best_depth.reshape(height, width)

    z = verts[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (verts @ k[:2].T) / z[:, None] - 0.5  # (V, 2), shifted so pixel centres are integers
    corners = uv[tri]  # (F, 3, 2)
    zf = z[tri]  # (F, 3)
    keep = (zf > near).all(1) & np.isfinite(corners).all((1, 2)) & np.isfinite(zf).all(1)
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]  # (F, 2)
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]  # twice the signed screen area
    keep &= np.abs(det) > 1e-12
    lo = np.ceil(corners.min(1) - 1e-9)  # (F, 2) first pixel centre of the bounding box
    hi = np.floor(corners.max(1) + 1e-9)
    keep &= (hi[:, 0] >= 0) & (hi[:, 1] >= 0) & (lo[:, 0] <= width - 1) & (lo[:, 1] <= height - 1)
    fid = np.flatnonzero(keep)
    if len(fid) == 0:
        return best_face.reshape(height, width), best_depth.reshape(height, width)
    size = np.array([width - 1, height - 1])
    lo = np.clip(lo[fid], 0, size).astype(np.int64)
    hi = np.clip(hi[fid], 0, size).astype(np.int64)
    corners, inv_z, e1, e2, det = corners[fid], 1.0 / zf[fid], e1[fid], e2[fid], det[fid]
    # Barycentric (b1, b2) = coef @ (cx, cy) + off, affine in the pixel centre.
    coef = np.stack([e2[:, 1], -e2[:, 0], -e1[:, 1], e1[:, 0]], 1) / det[:, None]  # (F', 4)
    off = -(coef.reshape(-1, 2, 2) @ corners[:, 0, :, None])[..., 0]  # (F', 2)
    nx, ny = (hi - lo + 1).T
    count = nx * ny  # pixel centres in each face's clipped bounding box

    # Faces in chunks of about _CHUNK candidate pixels; each chunk is reduced into the z-buffer.
    ends = np.cumsum(count)
    start = 0
    while start < len(fid):
        base = ends[start - 1] if start else 0
        stop = max(int(np.searchsorted(ends, base + _CHUNK, side="right")), start + 1)
        n = count[start:stop]
        local = np.repeat(np.arange(start, stop), n)  # (N,) face (position in fid) of each candidate
        k_in = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)  # index inside the bounding box
        w = nx[local]
        cx = lo[local, 0] + k_in % w
        cy = lo[local, 1] + k_in // w
        c, o = coef[local], off[local]
        b1 = c[:, 0] * cx + c[:, 1] * cy + o[:, 0]
        b2 = c[:, 2] * cx + c[:, 3] * cy + o[:, 1]
        b0 = 1.0 - b1 - b2
        inside = (b0 >= -eps) & (b1 >= -eps) & (b2 >= -eps)
        local, b0, b1, b2 = local[inside], b0[inside], b1[inside], b2[inside]
        iz = inv_z[local]
        depth = 1.0 / (b0 * iz[:, 0] + b1 * iz[:, 1] + b2 * iz[:, 2])
        pixel = cy[inside] * width + cx[inside]
        # Nearest candidate per pixel: sort by (pixel, depth); the sort is stable and candidates are
        # in face order, so equal depths keep the lowest face index first.
        order = np.lexsort((depth, pixel))
        pixel, depth, local = pixel[order], depth[order], local[order]
        first = np.ones(len(pixel), bool)
        first[1:] = pixel[1:] != pixel[:-1]
        pixel, depth, face = pixel[first], depth[first], fid[local[first]]
        better = depth < best_depth[pixel]  # strict: earlier chunks hold lower face indices
        best_depth[pixel[better]] = depth[better]
        best_face[pixel[better]] = face[better]
        start = stop
    return best_face.reshape(height, width), best_depth.reshape(height, width)


def _labels_from_faces(face_index: np.ndarray, labels: np.ndarray, background: int) -> np.ndarray:
    out = np.full(face_index.shape, background, dtype=labels.dtype)
    hit = face_index >= 0
    out[hit] = labels[face_index[hit]]
    return out


def _check_labels(face_labels: ArrayLike, num_faces: int, background: int) -> np.ndarray:
    labels = _as_array(face_labels, "face_labels")
    if labels.shape != (num_faces,) or not (np.issubdtype(labels.dtype, np.integer) or labels.size == 0):
        raise ValueError(
            f"face_labels must be an integer (F,) = ({num_faces},) array, got {labels.dtype} {labels.shape}"
        )
    if labels.size == 0:
        labels = labels.astype(np.int64)
    if isinstance(background, bool) or not isinstance(background, int | np.integer):
        raise ValueError(f"background must be an int label, got {background!r}")
    if not np.can_cast(np.min_scalar_type(background), labels.dtype):
        raise ValueError(f"background {background} does not fit face_labels' dtype {labels.dtype}")
    return labels


def rasterize_labels(
    vertices_cam: ArrayLike,
    faces: ArrayLike,
    K: ArrayLike,
    width: int,
    height: int,
    face_labels: ArrayLike,
    background: int = 0,
    near: float = 1e-3,
) -> np.ndarray:
    """A label map: each pixel centre takes the label of the nearest face covering it.

    Args:
        vertices_cam: (V, 3) camera-frame vertices in metres (OpenCV camera).
        faces: (F, 3) integer vertex indices, either winding.
        K: (3, 3) intrinsics in pixels.
        width, height: image size W, H in pixels.
        face_labels: (F,) integer label of each face (e.g. a body-part id).
        background: the label of pixels no face covers.
        near: faces with any vertex at ``z <= near`` metres are dropped.

    Returns:
        (H, W) labels, of ``face_labels``' dtype. See :func:`rasterize` for the coverage and depth rules.

    Raises:
        ValueError: on bad inputs (see :func:`rasterize`) or labels that are not (F,) integers.
    """
    labels = _check_labels(face_labels, len(_as_array(faces, "faces")), background)
    face_index, _ = rasterize(vertices_cam, faces, K, width, height, near=near)
    return _labels_from_faces(face_index, labels, background)


def rasterize_labels_batch(
    vertices_cam: ArrayLike,
    faces: ArrayLike,
    K: ArrayLike,
    width: int,
    height: int,
    face_labels: ArrayLike,
    background: int = 0,
    near: float = 1e-3,
) -> np.ndarray:
    """:func:`rasterize_labels` for B meshes sharing faces and face labels.

    Args:
        vertices_cam: (B, V, 3) camera-frame vertices in metres.
        faces: (F, 3) integer vertex indices.
        K: (3, 3) intrinsics shared by all meshes, or (B, 3, 3) one per mesh.
        width, height: image size W, H in pixels.
        face_labels: (F,) integer labels.
        background: the label of uncovered pixels.
        near: near-plane depth in metres.

    Returns:
        (B, H, W) label maps.

    Raises:
        ValueError: on a bad batch shape or any input :func:`rasterize_labels` rejects.
    """
    verts = _as_array(vertices_cam, "vertices_cam", np.float64)
    if verts.ndim != 3 or verts.shape[2] != 3:
        raise ValueError(f"vertices_cam must be (B, V, 3), got {verts.shape}")
    k = _as_array(K, "K", np.float64)
    if k.shape == (3, 3):
        k = np.broadcast_to(k, (len(verts), 3, 3))
    if k.shape != (len(verts), 3, 3):
        raise ValueError(f"K must be (3, 3) or (B, 3, 3) = ({len(verts)}, 3, 3), got {k.shape}")
    tri = _as_array(faces, "faces")
    labels = _check_labels(face_labels, len(tri), background)
    _check_size(width, height)
    out = np.full((len(verts), height, width), background, dtype=labels.dtype)
    for b in range(len(verts)):
        face_index, _ = rasterize(verts[b], tri, k[b], width, height, near=near)
        out[b] = _labels_from_faces(face_index, labels, background)
    return out
