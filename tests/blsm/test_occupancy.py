"""blsm.occupancy: the exact inside test and distances against shapes whose answers are known."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from blsm import occupancy


@pytest.fixture(scope="module")
def box():
    m = trimesh.creation.box(extents=(0.4, 1.0, 0.2))  # centred at the origin
    return np.asarray(m.vertices), np.asarray(m.faces)


def test_inside_and_signed_distance_of_a_box(box):
    v, f = box
    rng = np.random.default_rng(0)
    p = rng.uniform(-0.6, 0.6, (4000, 3))
    half = np.array([0.2, 0.5, 0.1])
    truth = (np.abs(p) < half).all(1)
    keep = np.abs(np.abs(p) - half).min(1) > 1e-6  # not on a face
    for exact in (True, False):
        assert np.array_equal(occupancy.inside(p, v, f, exact)[keep], truth[keep])
    s, _ = occupancy.signed_distance(p, v, f)
    q = np.abs(p) - half  # the box's exact signed distance
    want = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(1), 0.0)
    assert np.allclose(s, want, atol=1e-9)
    d = occupancy.distance(p, v, f, upper=0.05)
    assert np.allclose(d, np.minimum(np.abs(want), 0.05), atol=1e-9)
    assert np.allclose(occupancy.distance(p, v, f), np.abs(want), atol=1e-9)


def test_sample_points_follow_leap(box):
    v, f = box
    rng = np.random.default_rng(1)
    on = occupancy.surface_points(v, f, 3000, rng)
    assert np.abs(occupancy.signed_distance(on, v, f)[0]).max() < 1e-9
    # Faces drawn by area: the two 0.4 x 1.0 faces hold 0.4 / 0.68 of the area.
    assert np.mean(np.isclose(np.abs(on[:, 2]), 0.1)) == pytest.approx(0.4 / 0.68, abs=0.03)
    p = occupancy.sample_points(v, f, 500, 700, rng)
    assert p.shape == (1200, 3)
    near, uni = p[:500], p[500:]
    assert np.abs(occupancy.signed_distance(near, v, f)[0]).mean() < 3 * occupancy.NEAR_SIGMA_M
    lo, hi = v.min(0), v.max(0)
    pad = occupancy.BOX_PADDING * (hi - lo)
    assert (uni >= lo - pad).all() and (uni <= hi + pad).all() and (uni.min(0) < lo).all()


def test_bad_meshes_are_refused(box):
    v, f = box
    with pytest.raises(ValueError, match="faces index vertices"):
        occupancy.inside(np.zeros((1, 3)), v, f + 100)
    with pytest.raises(ValueError, match=r"\(V, 3\)"):
        occupancy.inside(np.zeros((1, 3)), v[:, :2], f)
