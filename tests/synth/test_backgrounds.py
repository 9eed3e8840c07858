"""synth.backgrounds: backplates cropped so that their horizon lies on the camera's (plates.json)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from blsm.camera import look_at_camera
from synth.backgrounds import plates as bg


def _plate(h: int = 300, w: int = 400, horizon: float = 0.4) -> np.ndarray:
    """Sky 0 above row ``horizon * h``, ground 1 below (channel 1)."""
    img = np.zeros((h, w, 3), np.float32)
    img[int(round(horizon * h)):, :, 1] = 1.0
    return img


@pytest.mark.parametrize("row", [10.0, 31.5, 50.0, 63.0, -20.0, 90.0])
def test_the_plates_horizon_lands_on_the_row(row):
    out = bg.crop_backplate_at_horizon(_plate(), 0.4, 64, 64, row, np.random.default_rng(1))
    assert out is not None and out.shape == (64, 64, 3)
    ground = out[:, 32, 1] > 0.5
    if row < 0:
        assert ground.all()
    elif row > 64:
        assert not ground.any()
    else:
        first = int(np.argmax(ground))
        # the horizon within one plate pixel (64 / (crop height) output pixels) plus the resampling filter
        assert abs(first - row) <= 2.5, (first, row)


def test_no_crop_when_the_horizon_cannot_reach_the_row():
    # a horizon at the very top of the plate cannot be put in the middle of a square image
    assert bg.crop_backplate_at_horizon(_plate(horizon=0.02), 0.02, 64, 64, 40.0, np.random.default_rng(0)) is None


def test_horizon_row_of_a_camera():
    # a camera 1.6 m high looking at a point 1 m high 5 m away: the horizon is above the centre by
    # f tan(pitch), and it does not depend on the camera's yaw
    for yaw in (0.0, 1.0, 2.5):
        eye = np.array([5 * np.sin(yaw), 1.6, 5 * np.cos(yaw)])
        cam = look_at_camera(eye, np.array([0.0, 1.0, 0.0]), fov_y_deg=50.0, width=100, height=80)
        pitch = np.arctan2(0.6, 5.0)
        row = bg.horizon_row(cam.K, cam.R)
        assert row == pytest.approx(cam.K[1, 2] - cam.K[1, 1] * np.tan(pitch), abs=1e-6)
        # the projection of a far point at the camera's height, straight ahead, is on that row
        far = eye + 1e4 * np.array([-np.sin(yaw), 0.0, -np.cos(yaw)])
        assert cam.project(far[None])[0, 1] == pytest.approx(row, abs=1e-2)
    down = look_at_camera(np.array([0.0, 10.0, 0.01]), np.zeros(3), fov_y_deg=50.0, width=100, height=80)
    assert bg.horizon_row(down.K, down.R) is None  # straight down: no horizon in view


def test_read_horizons(tmp_path):
    assert bg.read_horizons(tmp_path) == {}
    (tmp_path / bg.PLATES_JSON).write_text(json.dumps({"a.jpg": {"horizon": 0.4}, "b.jpg": {"horizon": None}, "c.jpg": {}}))
    assert bg.read_horizons(tmp_path) == {"a.jpg": 0.4}
    (tmp_path / bg.PLATES_JSON).write_text(json.dumps({"a.jpg": {"horizon": 1.4}}))
    with pytest.raises(ValueError, match="plates.json.*horizon 1.4"):
        bg.read_horizons(tmp_path)
    (tmp_path / bg.PLATES_JSON).write_text("{oops")
    with pytest.raises(ValueError, match="plates.json: not readable JSON"):
        bg.read_horizons(tmp_path)
