"""The shared rasteriser against a brute-force inside test at every pixel centre."""

from __future__ import annotations

import numpy as np

from synth.raster import rasterise, rasterise_uv


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


def test_uv_texels_match_a_loop_over_texel_centres():
    """rasterise_uv (texture painting, scan baking, texture transfer): texel (x, y) of a v-up UV map
    has its centre at u = (x + 0.5) / size, v = 1 - (y + 0.5) / size."""
    rng = np.random.default_rng(1)
    size = 16
    uv = rng.uniform(0, 1, (9, 2))
    faces_uv = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    texels, face, bary = rasterise_uv(uv, faces_uv, size)
    want = {}
    for y in range(size):
        for x in range(size):
            c = np.array([(x + 0.5) / size, 1 - (y + 0.5) / size])
            for f, tri in enumerate(uv[faces_uv]):
                m = np.stack([tri[1] - tri[0], tri[2] - tri[0]], 1)
                b1, b2 = np.linalg.solve(m, c - tri[0])
                if min(b1, b2) >= -1e-9 and b1 + b2 <= 1 + 1e-9:
                    want[y * size + x] = f  # later faces win
    assert dict(zip(texels.tolist(), face.tolist(), strict=True)) == want and len(want) > 10
    centres = np.stack([(texels % size + 0.5) / size, 1 - (texels // size + 0.5) / size], 1)
    np.testing.assert_allclose(np.einsum("nk,nkc->nc", bary, uv[faces_uv[face]]), centres, atol=1e-9)
