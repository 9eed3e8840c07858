"""Texture transfer from a scan to the BLSM UV atlas (the ``blsm`` pipeline of thesis Fig. 6.11).

Every texel of the model's atlas (``uvs``/``faces_uv``; the packaged model's atlas was made with
xatlas) is rasterised to a point on the subject's registration surface, in the scan's pose; the
closest point on the scan surface gives the scan's UV there and the texel takes the scan texture's
colour (bilinear). Texels outside every chart are filled from the nearest covered texel so that
bilinear lookups at chart borders show no seams.
"""

from __future__ import annotations

import numpy as np
import torch

from synth.raster import rasterise_uv
from synth.subjects import Subject, registration_output


def sample_bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of (H, W, C) ``image`` at (N, 2) v-up UVs; returns (N, C) float32."""
    h, w = image.shape[:2]
    x = np.clip(uv[:, 0] * w - 0.5, 0, w - 1)
    y = np.clip((1.0 - uv[:, 1]) * h - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    img = image.astype(np.float32)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bot = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def transfer_texture(subject: Subject, model, size: int = 1024) -> np.ndarray:
    """The subject's texture in the model's UV atlas: (size, size, 3) uint8 sRGB."""
    import trimesh
    from scipy import ndimage

    with torch.no_grad():
        reg_verts, _, _ = registration_output(model, subject.registration)
    reg = reg_verts.numpy().astype(np.float64)
    texels, face, bary = rasterise_uv(model.uvs.numpy(), model.faces_uv.numpy(), size)
    pts = np.einsum("tkc,tk->tc", reg[model.faces.numpy()[face]], bary)
    scan = trimesh.Trimesh(subject.vertices.astype(np.float64), subject.faces, process=False)
    closest, _, tri = trimesh.proximity.closest_point(scan, pts)
    b = trimesh.triangles.points_to_barycentric(scan.triangles[tri], closest)
    b = np.clip(b, 0.0, None)
    b /= b.sum(1, keepdims=True)
    uv = np.einsum("tkc,tk->tc", subject.uv[subject.faces_uv[tri]].astype(np.float64), b)
    colours = sample_bilinear(subject.texture, uv)
    img = np.zeros((size * size, 3), np.float32)
    img[texels] = colours
    covered = np.zeros(size * size, bool)
    covered[texels] = True
    idx = ndimage.distance_transform_edt(~covered.reshape(size, size), return_distances=False, return_indices=True)
    img = img.reshape(size, size, 3)[idx[0], idx[1]]
    return np.clip(np.round(img), 0, 255).astype(np.uint8)
