"""Tests for blsm.color (sRGB transfer functions)."""

from __future__ import annotations

import numpy as np
import pytest

from blsm.color import linear_to_srgb, srgb_to_linear


def _srgb_to_linear_naive(v: float) -> float:
    return v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4


def test_matches_the_standard_and_round_trips() -> None:
    x = np.linspace(0.0, 1.0, 257)
    np.testing.assert_allclose(srgb_to_linear(x), [_srgb_to_linear_naive(v) for v in x], rtol=1e-12)
    assert srgb_to_linear(np.array(0.5)) == pytest.approx(0.21404114, abs=1e-8)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-12)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12)


def test_clips_and_keeps_float_dtype() -> None:
    x = np.array([-0.5, 0.0, 1.0, 2.0], dtype=np.float32)
    for f in (srgb_to_linear, linear_to_srgb):
        y = f(x)
        assert y.dtype == np.float32 and y.shape == x.shape
        np.testing.assert_allclose(y, [0.0, 0.0, 1.0, 1.0], atol=1e-6)
    assert srgb_to_linear(np.array([0, 1])).dtype == np.float64
