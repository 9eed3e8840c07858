"""Tests for blsm.mitsuba_util (variant choice and OpenCV camera -> Mitsuba sensor)."""

from __future__ import annotations

import math
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from blsm import mitsuba_util
from blsm.camera import Camera, look_at_camera
from blsm.mitsuba_util import choose_variant, resolve_variant, sensor_params, to_world_matrix


def test_import_does_not_import_mitsuba() -> None:
    code = (
        "import sys, blsm.camera, blsm.color, blsm.mitsuba_util, blsm.render; "
        "assert 'mitsuba' not in sys.modules, 'mitsuba imported'"
    )
    root = Path(__file__).resolve().parents[2]
    proc = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr


def test_to_world_matrix_maps_opencv_axes() -> None:
    cam = look_at_camera(eye=(0.4, 1.2, 2.5), target=(0.0, 0.9, 0.0), width=64, height=80)
    m = to_world_matrix(cam)
    np.testing.assert_allclose(m[:3, 3], cam.center, atol=1e-12)
    np.testing.assert_allclose(m[3], [0.0, 0.0, 0.0, 1.0])
    # Mitsuba's local (x, y, z) are OpenCV's (-x, -y, +z): left, up, forward.
    np.testing.assert_allclose(m[:3, :3], cam.R.T @ np.diag([-1.0, -1.0, 1.0]), atol=1e-12)
    assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0)


def test_sensor_params_fov_and_principal_point() -> None:
    cam = look_at_camera(eye=(0, 0, 3), target=(0, 0, 0), fov_y_deg=30.0, width=64, height=80)
    x_fov, ppx, ppy = sensor_params(cam)
    assert x_fov == pytest.approx(math.degrees(2 * math.atan(32.0 / cam.K[0, 0])))
    assert (ppx, ppy) == (0.0, 0.0)  # centred camera: principal point at (W / 2, H / 2)
    K = cam.K.copy()
    K[0, 2] += 6.4  # principal point 10 % of the width to the right, 5 % of the height up
    K[1, 2] -= 4.0
    _, ppx, ppy = sensor_params(Camera(K=K, R=cam.R, t=cam.t, width=64, height=80))
    assert ppx == pytest.approx(-0.1) and ppy == pytest.approx(0.05)
    K[1, 1] *= 1.1
    with pytest.raises(ValueError, match="square pixels"):
        sensor_params(Camera(K=K, R=cam.R, t=cam.t, width=64, height=80))


def test_resolve_variant_rejects_a_broken_variant(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(mitsuba_util._PROBE_RESULTS, "bogus_variant", (False, "no such variant"))
    monkeypatch.setitem(mitsuba_util._PROBE_RESULTS, "good_variant", (True, ""))
    assert resolve_variant("good_variant") == "good_variant"
    with pytest.raises(RuntimeError, match="bogus_variant.*no such variant"):
        resolve_variant("bogus_variant")


def test_choose_variant_fallback_warns(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(mitsuba_util.VARIANT_ENV, raising=False)
    failure = (False, "LLVM ERROR: Cannot select: fminimum")
    monkeypatch.setitem(mitsuba_util._PROBE_RESULTS, "bogus_variant", failure)
    monkeypatch.setitem(mitsuba_util._PROBE_RESULTS, "good_variant", (True, ""))
    monkeypatch.setattr(mitsuba_util, "_CHOSEN_VARIANT", {})
    with pytest.warns(RuntimeWarning, match=r"bogus_variant.*fminimum.*libllvm19"):
        assert choose_variant(("bogus_variant", "good_variant")) == "good_variant"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert choose_variant(("bogus_variant", "good_variant")) == "good_variant"  # cached, silent
    with pytest.raises(RuntimeError, match="bogus_variant"):
        choose_variant(("bogus_variant",))
    # The environment variable forces a variant (still validated).
    monkeypatch.setenv(mitsuba_util.VARIANT_ENV, "good_variant")
    assert choose_variant(("bogus_variant",)) == "good_variant"
    monkeypatch.setenv(mitsuba_util.VARIANT_ENV, "bogus_variant")
    with pytest.raises(RuntimeError, match=mitsuba_util.VARIANT_ENV):
        choose_variant()


def test_probe_rejects_unknown_variant() -> None:
    ok, reason = mitsuba_util.probe_variant("not_a_real_variant_rgb", timeout=60)
    assert not ok and reason
