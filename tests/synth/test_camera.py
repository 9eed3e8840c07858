"""Camera sampling: OpenCV conventions, framing, truncation and rare views at their rates."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from synth.camera import CameraConfig, facing_yaw_deg, outline_index, sample_camera
from synth.dataset.shards import sample_rng


@pytest.fixture(scope="module")
def person(model):
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        out = model(pose=0.3 * torch.randn(1, 47, generator=g), transl=torch.tensor([[1.0, 0.9, -2.0]]))
    return out.vertices[0].double().numpy()


def test_untruncated_people_are_fully_in_frame_and_fill_it(person):
    cfg = CameraConfig(truncation_rate=0.0, rare_rate=0.0)
    for i in range(60):
        cam, info = sample_camera(person, cfg, sample_rng(0, i))
        assert np.allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-9) and np.linalg.det(cam.R) > 0
        assert (cam.world_to_camera(person)[:, 2] > 0).all()
        uv = cam.project(person)
        assert uv.min() >= 0 and uv[:, 0].max() <= cfg.width and uv[:, 1].max() <= cfg.height
        h = uv[:, 1].max() - uv[:, 1].min()
        w = uv[:, 0].max() - uv[:, 0].min()
        assert max(h, w) > 0.45 * cfg.height, (i, info)
        assert not info["truncated"] and info["view"] == "normal"


def test_up_is_up_in_normal_views_and_down_upside_down(person):
    for view, rare in (("normal", 0.0), ("upside_down", 1.0)):
        for i in range(40):
            cam, info = sample_camera(
                person, CameraConfig(rare_rate=rare, truncation_rate=0.0), sample_rng(1, i)
            )
            if info["view"] != view:
                continue
            top = person[person[:, 1].argmax()]
            bottom = person[person[:, 1].argmin()]
            v_top, v_bottom = cam.project(np.stack([top, bottom]))[:, 1]
            assert (v_top < v_bottom) == (view == "normal"), (view, info)


def test_truncation_and_rare_views_happen_at_their_rates(person):
    cfg = CameraConfig(truncation_rate=0.3, rare_rate=0.2)
    n, truncated, rare = 300, 0, 0
    for i in range(n):
        cam, info = sample_camera(person, cfg, sample_rng(2, i))
        uv = cam.project(person)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= cfg.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= cfg.height)
        if info["truncated"]:
            truncated += 1
            assert 0.0 < inside.mean() < 1.0, info  # partly out, partly in
            lo, hi = uv.min(0), uv.max(0)
            side = info["truncation_side"]
            axis = 0 if side in ("left", "right") else 1
            dim = cfg.width if axis == 0 else cfg.height
            beyond = -lo[axis] if side in ("left", "top") else hi[axis] - dim
            assert beyond / (hi[axis] - lo[axis]) == pytest.approx(info["truncation"], abs=1e-6), info
        else:
            assert inside.all(), info
        rare += info["view"] != "normal"
        if info["view"] == "above":
            assert info["elevation_deg"] > 50
    assert abs(truncated / n - 0.3) < 0.08
    assert abs(rare / n - 0.2) < 0.07


def test_same_seed_same_camera_and_bad_config(person):
    a, _ = sample_camera(person, CameraConfig(), sample_rng(5, 9))
    b, _ = sample_camera(person, CameraConfig(), sample_rng(5, 9))
    np.testing.assert_array_equal(a.K, b.K)
    np.testing.assert_array_equal(a.R, b.R)
    with pytest.raises(ValueError, match="focal_mm"):
        CameraConfig(focal_mm=(50.0, 20.0))
    with pytest.raises(ValueError, match="truncation_rate"):
        CameraConfig(truncation_rate=1.5)
    with pytest.raises(ValueError, match="points"):
        sample_camera(np.zeros((5, 2)), CameraConfig(), sample_rng(0, 0))


def test_frontal_views_at_their_rate_about_the_facing_and_off_leaves_the_draws(person):
    # Off (the default), the cameras are those of a config without the option, draw for draw.
    for i in range(20):
        a, ia = sample_camera(person, CameraConfig(), sample_rng(7, i))
        b, ib = sample_camera(person, CameraConfig(frontal_rate=0.0, frontal_yaw_deg=(-10.0, 10.0)), sample_rng(7, i), facing_deg=70.0)
        np.testing.assert_array_equal(a.R, b.R)
        assert ia == ib
    # On: about half of the yaws within 45 degrees of the facing (the rest uniform all around, a
    # quarter of which also land there), and the camera then in front of a body facing that way.
    cfg = CameraConfig(frontal_rate=0.5, rare_rate=0.0, truncation_rate=0.0)
    n, front = 400, 0
    for i in range(n):
        cam, info = sample_camera(person, cfg, sample_rng(8, i), facing_deg=120.0)
        d = (info["yaw_deg"] - 120.0 + 180.0) % 360.0 - 180.0
        front += abs(d) <= 45.0
        if abs(d) <= 45.0:
            eye = -cam.R.T @ cam.t
            centre = 0.5 * (person.min(0) + person.max(0))
            f = np.array([np.sin(np.radians(120.0)), 0.0, np.cos(np.radians(120.0))])
            assert f @ (eye - centre) > 0
    assert abs(front / n - 0.625) < 0.07
    assert facing_yaw_deg(np.zeros(3)) == 0.0
    assert facing_yaw_deg(np.array([0.0, np.pi / 2, 0.0])) == pytest.approx(90.0)
    with pytest.raises(ValueError, match="frontal_rate"):
        CameraConfig(frontal_rate=1.5)
    with pytest.raises(ValueError, match="frontal_yaw_deg"):
        CameraConfig(frontal_yaw_deg=(30.0, -30.0))


def test_the_hull_points_frame_the_person_exactly_as_all_vertices_do(person, monkeypatch):
    """sample_camera works on the hull vertices (synth.camera.outline_index): the same camera as
    from every vertex, and the hull of a degenerate (flat) set is every point."""
    import synth.camera

    idx = outline_index(person)
    assert 4 <= len(idx) < len(person) // 5
    cfg = CameraConfig(rare_rate=0.3, truncation_rate=0.3)
    with monkeypatch.context() as m:  # the reference: every vertex
        m.setattr(synth.camera, "outline_index", lambda p: np.arange(len(p)))
        ref = [sample_camera(person, cfg, sample_rng(7, i)) for i in range(20)]
    for i, (a, info_a) in enumerate(ref):
        b, info_b = sample_camera(person, cfg, sample_rng(7, i))
        assert np.allclose(a.K, b.K, rtol=0, atol=1e-9) and np.allclose(a.t, b.t, rtol=0, atol=1e-12)
        assert np.array_equal(a.R, b.R) and info_a == info_b
    flat = np.c_[np.random.default_rng(0).normal(size=(100, 2)), np.zeros(100)]
    assert len(outline_index(flat)) == 100
