"""Tests for blsm.render (Mitsuba clay renderer)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from blsm import render
from blsm.camera import Camera, auto_camera, look_at_camera
from blsm.mitsuba_util import choose_variant
from blsm.render import render_grid, render_meshes

W, H = 64, 80
BG = (1.0, 1.0, 1.0)


@pytest.fixture(scope="module")
def variant() -> str:
    """A Mitsuba variant that can render here; skips the test otherwise."""
    try:
        return choose_variant()
    except RuntimeError as exc:
        pytest.skip(f"no usable Mitsuba variant: {exc}")


def _sphere(center: tuple[float, float, float], radius: float = 0.08) -> tuple[np.ndarray, np.ndarray]:
    ico = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    return np.asarray(ico.vertices) + np.asarray(center), np.asarray(ico.faces)


def _mask_centroid(image: np.ndarray) -> tuple[np.ndarray, int]:
    """Centroid (u, v) of non-background pixels, pixel centres at +0.5."""
    mask = np.any(np.abs(image - np.asarray(BG, dtype=np.float32)) > 1e-3, axis=2)
    rows, cols = np.nonzero(mask)
    assert rows.size > 0, "nothing rendered"
    return np.array([cols.mean() + 0.5, rows.mean() + 0.5]), int(rows.size)


def test_import_does_not_import_mitsuba() -> None:
    code = "import sys, blsm.render; assert 'mitsuba' not in sys.modules, 'mitsuba imported'"
    root = Path(__file__).resolve().parents[2]
    proc = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr


@pytest.mark.parametrize(
    "center",
    [(0.0, 0.0, 0.0), (0.35, 0.0, 0.0), (0.0, -0.45, 0.0), (-0.25, 0.3, 0.4)],
)
def test_render_position_matches_projection(variant: str, center: tuple[float, float, float]) -> None:
    cam = look_at_camera(eye=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), fov_y_deg=30.0, width=W, height=H)
    img = render_meshes([_sphere(center)], cam, spp=4, variant=variant, background=BG)
    assert img.shape == (H, W, 3) and img.dtype == np.float32
    assert 0.0 <= img.min() and img.max() <= 1.0
    centroid, _ = _mask_centroid(img)
    expected = cam.project(np.array([center]))[0]
    assert np.linalg.norm(centroid - expected) < 1.5, (centroid, expected)
    # Side checks (catch x/y flips): +X world is right, -Y world is down.
    if center[0] > 0:
        assert centroid[0] > W / 2 + 5
    if center[1] < 0:
        assert centroid[1] > H / 2 + 5


def test_render_off_centre_principal_point(variant: str) -> None:
    base = look_at_camera(eye=(0.3, 0.5, 2.5), target=(0.0, 0.0, 0.0), width=W, height=H)
    K = base.K.copy()
    K[0, 2] += 7.0
    K[1, 2] -= 5.0
    cam = Camera(K=K, R=base.R, t=base.t, width=W, height=H)
    center = (0.15, -0.1, 0.05)
    img = render_meshes([_sphere(center)], cam, spp=4, variant=variant)
    centroid, _ = _mask_centroid(img)
    np.testing.assert_allclose(centroid, cam.project(np.array([center]))[0], atol=1.5)


def test_render_colors_and_vertex_colors(variant: str) -> None:
    cam = look_at_camera(eye=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), width=W, height=H)
    verts, faces = _sphere((0.0, 0.0, 0.0), radius=0.3)
    vc = np.tile(np.array([[0.9, 0.1, 0.1]]), (verts.shape[0], 1))
    img = render_meshes(
        [(verts, faces), _sphere((0.0, 0.5, 0.0))],
        cam,
        vertex_colors=[vc, None],
        colors=[(0.5, 0.5, 0.5), (0.1, 0.2, 0.9)],
        spp=4,
        variant=variant,
        background=(0.0, 0.0, 0.0),
    )
    centre_px = img[H // 2, W // 2]
    assert centre_px[0] > 2 * centre_px[1] and centre_px[0] > 2 * centre_px[2]  # red sphere
    top = cam.project(np.array([[0.0, 0.5, 0.0]]))[0].astype(int)
    top_px = img[top[1], top[0]]
    assert top_px[2] > top_px[0] and top_px[2] > top_px[1]  # blue sphere
    assert np.all(img[0, 0] == 0.0)  # background colour honoured
    with pytest.raises(ValueError):
        render_meshes([(verts, faces)], cam, vertex_colors=[vc[:-1]], variant=variant)
    with pytest.raises(ValueError):
        render_meshes([(verts, faces + verts.shape[0])], cam, variant=variant)


def test_render_grid_size_and_labels(variant: str, tmp_path: Path) -> None:
    from PIL import Image

    items = [
        [_sphere((0.0, 0.0, 0.0))],
        [_sphere((0.0, 0.0, 0.0)), _sphere((0.3, 0.1, 0.0))],
        [(trimesh.creation.box(extents=(0.3, 0.6, 0.2)).vertices, trimesh.creation.box().faces)],
    ]
    out = tmp_path / "grid.png"
    tw, th = 40, 48
    path = render_grid(items, out, labels=["a", "b", "c"], cols=2, tile_size=(tw, th), spp=4, variant=variant,
                       label_height=12)
    assert path == out and out.exists() and not out.with_suffix(".tmp.png").exists()
    with Image.open(out) as im:
        assert im.size == (2 * tw, 2 * (th + 12))
    # Without labels there is no strip; a custom camera_fn is used as given.
    out2 = tmp_path / "grid2.png"
    render_grid(items, out2, cols=3, tile_size=(tw, th), spp=4, variant=variant,
                camera_fn=lambda item: auto_camera(item, tw, th, elevation_deg=0.0))
    with Image.open(out2) as im:
        assert im.size == (3 * tw, th)
    with pytest.raises(ValueError):
        render_grid(items, out2, cols=2, tile_size=(tw, th), variant=variant,
                    camera_fn=lambda item: auto_camera(item, tw + 1, th))


def test_save_png_roundtrip(tmp_path: Path) -> None:
    from PIL import Image

    img = np.zeros((5, 7, 3), dtype=np.float32)
    img[2, 3] = (1.0, 0.5, 0.0)
    out = render.save_png(img, tmp_path / "sub" / "x.png")
    arr = np.asarray(Image.open(out))
    assert arr.shape == (5, 7, 3) and tuple(arr[2, 3]) == (255, 128, 0)
    with pytest.raises(ValueError):
        render.save_png(np.zeros((5, 7, 2)), tmp_path / "bad.png")
