"""Tests for blsm.camera (OpenCV pinhole cameras; pure numpy)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from blsm.camera import Camera, auto_camera, look_at_camera

W, H = 64, 80


def test_project_matches_manual_pinhole() -> None:
    cam = look_at_camera(eye=(0.4, 1.2, 2.5), target=(0.0, 0.9, 0.0), fov_y_deg=35.0, width=W, height=H)
    # Principal point convention: centred camera -> (W/2, H/2), target on it.
    assert cam.K[0, 2] == pytest.approx(W / 2) and cam.K[1, 2] == pytest.approx(H / 2)
    np.testing.assert_allclose(cam.project(np.array([[0.0, 0.9, 0.0]])), [[W / 2, H / 2]], atol=1e-9)
    # Focal length from the vertical field of view.
    assert cam.K[1, 1] == pytest.approx(0.5 * H / np.tan(np.radians(35.0) / 2))
    assert np.allclose(cam.R @ cam.R.T, np.eye(3)) and np.linalg.det(cam.R) == pytest.approx(1.0)
    np.testing.assert_allclose(cam.center, [0.4, 1.2, 2.5], atol=1e-12)

    pts = np.random.default_rng(0).normal(size=(20, 3)) * 0.3 + np.array([0.0, 0.9, 0.0])
    x = (cam.K @ (cam.R @ pts.T + cam.t[:, None])).T
    np.testing.assert_allclose(cam.project(pts), x[:, :2] / x[:, 2:], rtol=1e-12, atol=1e-9)

    # OpenCV axes: world +Y (up) goes to smaller v; camera at +Z sees world +X on the right.
    front = look_at_camera(eye=(0, 0, 3), target=(0, 0, 0), width=W, height=H)
    uv = front.project(np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.2, 0.0]]))
    assert uv[1, 0] > uv[0, 0] and uv[2, 1] < uv[0, 1]


def test_camera_validation() -> None:
    with pytest.raises(ValueError):
        look_at_camera(eye=(0, 3, 0), target=(0, 0, 0), up=(0, 1, 0))
    with pytest.raises(ValueError):
        Camera(K=np.eye(3), R=np.diag([1.0, 1.0, -1.0]), t=np.zeros(3), width=4, height=4)


def test_auto_camera_frames_box() -> None:
    verts = np.array(trimesh.creation.box(extents=(0.4, 1.7, 0.3)).vertices) + np.array([0.2, 0.9, -0.1])
    cam = auto_camera([(verts, np.zeros((1, 3), dtype=int))], 96, 128)
    uv = cam.project(verts)
    assert (uv[:, 0] > 0).all() and (uv[:, 0] < 96).all()
    assert (uv[:, 1] > 0).all() and (uv[:, 1] < 128).all()
    # Tight: the box fills most of the image height.
    assert uv[:, 1].max() - uv[:, 1].min() > 0.8 * 128


def test_camera_is_read_only_float64() -> None:
    cam = Camera(K=np.eye(3, dtype=np.float32), R=np.eye(3), t=[0, 0, 1], width=4.0, height=3)
    assert cam.K.dtype == np.float64 and cam.t.shape == (3,) and (cam.width, cam.height) == (4, 3)
    with pytest.raises(ValueError):
        cam.K[0, 0] = 2.0
    with pytest.raises(ValueError, match="points must have shape"):
        cam.project(np.zeros((3, 2)))
