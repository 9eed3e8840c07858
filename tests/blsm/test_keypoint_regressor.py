"""Tests of blsm/learn/markerless/keypoint_regressor.py: A_kp of Eq. 6.4 learnt for a detector."""

from __future__ import annotations

import numpy as np
import pytest

from blsm.learn.markerless.keypoint_regressor import (
    fit_keypoint_regressor,
    load_keypoint_regressor,
    save_keypoint_regressor,
)


def _scans(rng: np.random.Generator, n: int, v: int = 30) -> np.ndarray:
    """(n, v, 3) random 'posed meshes': a common layout, moved and deformed per scan."""
    base = rng.normal(size=(v, 3))
    return np.stack([base + 0.3 * rng.normal(size=(v, 3)) + rng.normal(size=3) for _ in range(n)])


def test_recovers_an_affine_vertex_triplet_and_predicts_new_scans():
    rng = np.random.default_rng(0)
    verts = _scans(rng, 24)
    truth_v, truth_w = np.array([[3, 7, 11], [0, 5, 20]]), np.array([[0.5, 0.8, -0.3], [0.2, 0.3, 0.5]])
    points = np.einsum("nkvc,kv->nkc", verts[:, truth_v], truth_w)
    points[2, 1] = np.nan  # a keypoint the detector missed in one scan
    kps, report = fit_keypoint_regressor(points[:20], verts[:20], ["a", "b"], candidates=30)
    assert max(report["residual_mm"].values()) < 1e-6
    assert report["scans"] == {"a": 20, "b": 19}
    pred = (verts[20:, kps.vertices.numpy()] * kps.bary.numpy()[None, ..., None]).sum(2)
    np.testing.assert_allclose(pred, points[20:], atol=1e-5)
    assert (kps.joint == -1).all()


def test_file_round_trip_and_bad_files(tmp_path):
    rng = np.random.default_rng(1)
    verts = _scans(rng, 6)
    points = verts[:, [1, 2]] + 0.01 * rng.normal(size=(6, 2, 3))
    kps, report = fit_keypoint_regressor(points, verts, ["a", "b"], candidates=10)
    path = save_keypoint_regressor(kps, tmp_path / "r.npz", report)
    back = load_keypoint_regressor(path, verts.shape[1])
    assert back.names == ["a", "b"]
    np.testing.assert_array_equal(back.vertices.numpy(), kps.vertices.numpy())
    np.testing.assert_allclose(back.bary.numpy(), kps.bary.numpy())
    with pytest.raises(ValueError, match="r.npz: vertex indices outside"):
        load_keypoint_regressor(path, 2)
    with pytest.raises(ValueError, match="none.npz"):
        load_keypoint_regressor(tmp_path / "none.npz", 10)
    with pytest.raises(ValueError, match="keypoint a: found in 2 training scans"):
        pts = points.copy()
        pts[2:, 0] = np.nan
        fit_keypoint_regressor(pts, verts, ["a", "b"], candidates=10)
