"""blsm.spiral.sampling and the pooling modules: Q^d / Q^u of thesis Sec. 4.3.2."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from recovery_helpers import sphere

from blsm.spiral.conv import Pool, Unpool
from blsm.spiral.sampling import build_levels, decimate, upsampling


@pytest.fixture(scope="module")
def levels():
    v, f = sphere(3)  # 642 vertices
    return v, f, build_levels(v, f, (4, 2))


def test_decimation_keeps_original_vertices_at_their_places(levels):
    v, f, lv = levels
    n1 = len(lv[0].down)
    assert abs(n1 - len(v) / 4) <= 0.05 * len(v)
    assert len(lv[1].down) == pytest.approx(n1 / 2, rel=0.1)
    assert (np.diff(lv[0].down) > 0).all()  # ascending, unique
    assert lv[0].faces.max() == n1 - 1 and (lv[0].faces >= 0).all()


def test_down_then_up_returns_kept_vertices_exactly(levels):
    v, f, lv = levels
    first = lv[0]
    x = torch.randn(len(v), 2, 4)  # (n, B, C)
    coarse = Pool(torch.as_tensor(first.down))(x)
    torch.testing.assert_close(coarse, x[first.down], rtol=0, atol=0)
    up = Unpool(torch.as_tensor(first.up_index), torch.as_tensor(first.up_weight))(coarse)
    torch.testing.assert_close(up[first.down], x[first.down], rtol=0, atol=0)
    np.testing.assert_allclose(first.up_weight.sum(1), 1.0, atol=1e-12)
    assert (first.up_weight >= 0).all()


def test_gathers_equal_the_dense_matrices(levels):
    v, f, lv = levels
    first = lv[0]
    x = np.random.default_rng(0).normal(size=(len(v), 3))
    qd, qu = first.down_matrix(), first.up_matrix()
    assert qd.shape == (len(v), len(first.down)) and set(np.unique(qd)) == {0.0, 1.0}
    np.testing.assert_allclose(qd.T @ x, x[first.down])
    xc = x[first.down]
    up = Unpool(torch.as_tensor(first.up_index), torch.as_tensor(first.up_weight))(torch.as_tensor(xc)[:, None])[:, 0]
    np.testing.assert_allclose(up.numpy(), qu.T @ xc, atol=1e-6)


def test_upsampling_reproduces_points_on_the_coarse_surface():
    v, f = sphere(2)
    down, cf = decimate(v, f, 4)
    idx, w = upsampling(v, down, cf)
    # a point on a coarse triangle is reproduced by its barycentric weights
    coarse = v[down]
    approx = (coarse[idx] * w[..., None]).sum(1)
    err = np.linalg.norm(approx - v, axis=1)
    assert err[down].max() < 1e-12
    assert err.max() < 0.2  # every discarded vertex lies near the coarse surface of a unit sphere
