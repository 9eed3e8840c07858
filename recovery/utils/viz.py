"""Overlays of predicted meshes without Mitsuba (it is not on every training machine): the z-buffer of
:mod:`recovery.utils.raster`, flat Lambertian shading per face, the thesis' part colours.

Images are (H, W, 3) uint8; vertices are camera-frame metres (OpenCV: x right, y down, z forward);
``K`` maps them to pixels with pixel centres at integer + 0.5.
"""

from __future__ import annotations

import numpy as np

from recovery.utils.raster import rasterize
from synth.dataset.format import PART_PALETTE


def face_parts(faces: np.ndarray, vertex_parts: np.ndarray) -> np.ndarray:
    """(F,) part label 1 + k of each face: the part most of its three vertices belong to (its first
    vertex's when all differ); 0 is background."""
    p = vertex_parts[faces]  # (F, 3)
    major = np.where(p[:, 1] == p[:, 2], p[:, 1], p[:, 0])
    return (major + 1).astype(np.int64)


def shade(vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, width: int, height: int,
          color: tuple[float, float, float] | np.ndarray = (0.75, 0.75, 0.8)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flat-shaded render (headlight): (H, W, 3) float in [0, 1], the (H, W) coverage mask and the
    (H, W) depth (inf where uncovered).

    ``color`` is one RGB for the whole mesh or (F, 3) per face.
    """
    face_index, depth = rasterize(vertices, faces, K, width, height)
    v = np.asarray(vertices, np.float64)
    tri = v[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    view = -tri.mean(1)
    view /= np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-12)
    n = np.where((n * view).sum(1, keepdims=True) < 0, -n, n)  # either winding faces the viewer
    lam = 0.25 + 0.75 * np.clip((n * view).sum(1), 0, 1)  # a headlight: faces towards the viewer are brightest
    col = np.broadcast_to(np.asarray(color, np.float64), (len(faces), 3))
    face_rgb = col * lam[:, None]
    mask = face_index >= 0
    out = np.zeros((height, width, 3))
    out[mask] = face_rgb[face_index[mask]]
    return out, mask, depth


def overlay(image: np.ndarray, vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, alpha: float = 0.7,
            color: tuple[float, float, float] | np.ndarray = (0.75, 0.75, 0.8)) -> np.ndarray:
    """The shaded mesh over ``image`` (H, W, 3) uint8 with opacity ``alpha``."""
    h, w = image.shape[:2]
    rgb, mask, _ = shade(vertices, faces, K, w, h, color)
    out = image.astype(np.float64) / 255.0
    out[mask] = (1 - alpha) * out[mask] + alpha * rgb[mask]
    return (out * 255 + 0.5).clip(0, 255).astype(np.uint8)


def parts_overlay(image: np.ndarray, vertices: np.ndarray, faces: np.ndarray, K: np.ndarray,
                  face_labels: np.ndarray, alpha: float = 0.6) -> np.ndarray:
    """The mesh's parts (:data:`synth.dataset.format.PART_PALETTE`) over ``image``, shaded."""
    return overlay(image, vertices, faces, K, alpha, PART_PALETTE[face_labels].astype(np.float64) / 255.0)


def label_image(labels: np.ndarray) -> np.ndarray:
    """(H, W) part labels (0 background) -> (H, W, 3) uint8 in the part palette."""
    return PART_PALETTE[np.clip(labels, 0, len(PART_PALETTE) - 1)]


def side_view(meshes: list[tuple[np.ndarray, tuple[float, float, float]]], faces: np.ndarray, size: int,
              yaw_deg: float = 90.0) -> np.ndarray:
    """Meshes (camera frame, each with a colour) seen from the side: each centred on its own centroid
    (so a prediction and its label overlap whatever their depth error), rotated by ``yaw_deg`` about
    the camera's vertical axis, framed to fit. Returns (size, size, 3) uint8."""
    a = np.radians(yaw_deg)
    r = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    moved = [((m - m.mean(0)) @ r.T, col) for m, col in meshes]
    pts = np.concatenate([m for m, _ in moved])
    extent = max(np.ptp(pts[:, 0]), np.ptp(pts[:, 1]), 1e-3)
    dist = 3.0
    f = 0.8 * size * dist / extent
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    mid = (pts.max(0) + pts.min(0)) / 2
    out = np.full((size, size, 3), 1.0)
    depth = np.full((size, size), np.inf)
    for m, col in moved:
        v = m - np.array([mid[0], mid[1], 0]) + np.array([0, 0, dist])
        rgb, mask, d = shade(v, faces, K, size, size, col)
        nearer = mask & (d < depth)
        out[nearer] = rgb[nearer]
        depth[nearer] = d[nearer]
    return (out * 255 + 0.5).clip(0, 255).astype(np.uint8)


PERSON_COLORS = np.array([[0.95, 0.55, 0.25], [0.35, 0.65, 0.95], [0.45, 0.85, 0.45], [0.9, 0.4, 0.75],
                          [0.95, 0.85, 0.3], [0.55, 0.45, 0.9], [0.3, 0.85, 0.85], [0.85, 0.35, 0.35]])
"""RGB in [0, 1], one per person of a multi-person overlay (cycled)."""


def people_overlay(image: np.ndarray, meshes: list[np.ndarray], faces: np.ndarray, K: np.ndarray,
                   alpha: float = 0.7, colors: np.ndarray = PERSON_COLORS) -> np.ndarray:
    """Every mesh over ``image``, each in its colour (``colors[i % len]``), depth-ordered per pixel: a
    nearer person hides a farther one (one z-buffer across the meshes).

    Args:
        image: (H, W, 3) uint8.
        meshes: each (V, 3) camera-frame vertices, metres.
        faces: (F, 3) shared by the meshes.
        K: (3, 3) the image's intrinsics.

    Returns:
        (H, W, 3) uint8.
    """
    h, w = image.shape[:2]
    rgb = np.zeros((h, w, 3))
    depth = np.full((h, w), np.inf)
    for i, verts in enumerate(meshes):
        col, mask, d = shade(verts, faces, K, w, h, colors[i % len(colors)])
        nearer = mask & (d < depth)
        rgb[nearer] = col[nearer]
        depth[nearer] = d[nearer]
    out = image.astype(np.float64) / 255.0
    hit = np.isfinite(depth)
    out[hit] = (1 - alpha) * out[hit] + alpha * rgb[hit]
    return (out * 255 + 0.5).clip(0, 255).astype(np.uint8)


def draw_boxes(image: np.ndarray, boxes: list[np.ndarray], colors: np.ndarray = PERSON_COLORS,
               width: int = 2) -> np.ndarray:
    """``image`` (H, W, 3) uint8 with each ``x0, y0, x1, y1`` box (pixels) outlined in its colour."""
    out = image.copy()
    h, w = out.shape[:2]
    for i, b in enumerate(boxes):
        c = (np.asarray(colors[i % len(colors)]) * 255 + 0.5).astype(np.uint8)
        x0, y0 = int(np.clip(np.floor(b[0]), 0, w - 1)), int(np.clip(np.floor(b[1]), 0, h - 1))
        x1, y1 = int(np.clip(np.ceil(b[2]) - 1, x0, w - 1)), int(np.clip(np.ceil(b[3]) - 1, y0, h - 1))
        t = max(1, min(width, (x1 - x0 + 1) // 2, (y1 - y0 + 1) // 2))
        out[y0:y0 + t, x0:x1 + 1] = c
        out[y1 - t + 1:y1 + 1, x0:x1 + 1] = c
        out[y0:y1 + 1, x0:x0 + t] = c
        out[y0:y1 + 1, x1 - t + 1:x1 + 1] = c
    return out
