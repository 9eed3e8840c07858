"""The shared rasteriser against a brute-force inside test at every pixel centre."""

from __future__ import annotations

import numpy as np

from synth.raster import rasterise


def _inside(t: np.ndarray, width: int, height: int) -> set[int]:
    ys, xs = np.mgrid[0:height, 0:width]
    p = np.stack([xs.ravel(), ys.ravel()], 1).astype(float)
    a, b, c = t
    d = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    l1 = ((p[:, 0] - a[0]) * (c[1] - a[1]) - (p[:, 1] - a[1]) * (c[0] - a[0])) / d
    l2 = ((b[0] - a[0]) * (p[:, 1] - a[1]) - (b[1] - a[1]) * (p[:, 0] - a[0])) / d
    return set(np.flatnonzero((l1 >= 0) & (l2 >= 0) & (l1 + l2 <= 1)).tolist())


def test_pixels_faces_and_barycentrics_match_brute_force():
    rng = np.random.default_rng(0)
    width, height = 20, 16
    for _ in range(50):
        t = rng.uniform(-5, 25, (3, 2))
        tris = np.stack([np.full((3, 2), np.nan), t[::-1], t + 100.0])  # NaN, reversed winding, off image
        pixel, face, bary = rasterise(tris, width, height)
        assert set(pixel.tolist()) == _inside(t, width, height)
        assert (face == 1).all()
        xy = np.stack([pixel % width, pixel // width], 1)
        np.testing.assert_allclose(bary @ tris[1], xy, atol=1e-9)


def test_later_faces_win_and_degenerate_faces_cover_nothing():
    square = np.array([[[0, 0], [9, 0], [9, 9]], [[0, 0], [9, 9], [0, 9]]], float)
    pixel, face, _ = rasterise(np.concatenate([square, square]), 10, 10)
    assert len(pixel) == 100 and set(face.tolist()) == {2, 3}
    flat = np.array([[[0, 0], [5, 5], [9, 9]]], float)
    assert len(rasterise(flat, 10, 10)[0]) == 0
