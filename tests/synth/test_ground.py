"""synth.ground: environment lookups as Mitsuba's envmap, the shadow catcher's ratio, camera height."""

from __future__ import annotations

import math

import numpy as np
import pytest

from blsm.camera import Camera, look_at_camera
from synth.camera import CameraConfig, sample_camera
from synth.ground import EnvSampler, env_lookup, ground_points, pixel_rays, shadow_ratio


def _camera(width=40, height=32, eye=(1.0, 1.7, 4.0), target=(0.0, 0.8, 0.0), shift=(5.0, -3.0)) -> Camera:
    cam = look_at_camera(np.array(eye), np.array(target), width=width, height=height)
    K = cam.K.copy()
    K[0, 2] += shift[0]
    K[1, 2] += shift[1]
    return Camera(K=K, R=cam.R, t=cam.t, width=width, height=height)


def test_env_lookup_is_what_mitsuba_shows_at_pixel_centres():
    from blsm.mitsuba_util import load_mitsuba, resolve_variant, sensor_params, to_world_matrix

    mi = load_mitsuba(resolve_variant(None))
    rng = np.random.default_rng(0)
    env = rng.random((32, 64, 3)).astype(np.float32)  # texel noise: any misplacement shows
    cam = _camera()
    x_fov, ppx, ppy = sensor_params(cam)
    rot, scale = 0.7, 1.3
    c, s = math.cos(rot), math.sin(rot)
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "path"},
        "sensor": {
            "type": "perspective", "fov": x_fov, "fov_axis": "x", "principal_point_offset_x": ppx,
            "principal_point_offset_y": ppy, "to_world": mi.ScalarTransform4f(to_world_matrix(cam)),
            "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
            "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height, "pixel_format": "rgb",
                     "rfilter": {"type": "box"}},
        },
        "env": {"type": "envmap", "bitmap": mi.Bitmap(env), "scale": scale,
                "to_world": mi.ScalarTransform4f(np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]]))},
    })  # fmt: skip
    theirs = np.asarray(mi.render(scene, spp=1))
    _, dirs = pixel_rays(cam)
    ours = env_lookup(env, dirs.reshape(-1, 3), rot, scale).reshape(theirs.shape)
    np.testing.assert_allclose(ours, theirs, atol=1e-4)


def test_ground_points_lie_on_the_plane_along_the_pixel_rays():
    cam = _camera()
    mask, pts = ground_points(cam, max_distance=100.0)
    assert mask.any() and not mask.all()  # the horizon crosses the image
    assert np.abs(pts[mask][:, 1]).max() < 1e-9
    uvw = cam.K @ (cam.R @ pts[mask].T + cam.t[:, None])
    uv = (uvw[:2] / uvw[2]).T
    vv, uu = np.nonzero(mask)
    np.testing.assert_allclose(uv, np.stack([uu + 0.5, vv + 0.5], 1), atol=1e-6)
    near, _ = ground_points(cam, max_distance=3.0)
    assert near.sum() < mask.sum() and not (near & ~mask).any()


def test_env_sampler_draws_only_from_lit_texels_above_the_horizon():
    env = np.zeros((64, 128, 3), np.float32)
    env[10, 40] = 50.0  # a small sun, 28 degrees from the zenith
    env[50, 10] = 1e6  # below the horizon: never drawn
    d = EnvSampler(env, rotation=0.3).sample(500, np.random.default_rng(0))
    assert (d[:, 1] > 0).all()
    lum = env_lookup(env, d, rotation=0.3)
    assert (lum.max(axis=1) > 0).all()  # every direction sees the sun texel
    with pytest.raises(ValueError, match="no light above the horizon"):
        EnvSampler(np.zeros((8, 16, 3), np.float32), 0.0)


def _disc_test(centre, radius):
    """Analytic ray test: a horizontal disc at height centre[1] blocks the rays that cross it."""

    def test(o, d):
        t = (centre[1] - o[:, 1]) / d[:, 1]
        p = o + t[:, None] * d
        return (t > 0) & (np.hypot(p[:, 0] - centre[0], p[:, 2] - centre[2]) < radius)

    return test


def test_shadow_ratio_under_a_disc_in_a_uniform_sky_is_the_cosine_weighted_cone():
    # A constant environment and a horizontal disc of radius R at height h above a ground point: the
    # blocked share of the cosine-weighted hemisphere is sin^2(atan(R / h)) = 0.5 for R = h.
    env = np.ones((64, 128, 3), np.float32)
    cam = look_at_camera(np.array([0.0, 5.0, 0.01]), np.array([0.0, 0.0, 0.0]), width=9, height=9)
    cam = Camera(K=np.array([[2000.0, 0, 4.5], [0, 2000.0, 4.5], [0, 0, 1]]), R=cam.R, t=cam.t, width=9, height=9)
    disc = (np.array([0.0, 1.0, 0.0]), 1.0)
    ratio, mask = shadow_ratio(_disc_test(*disc), cam, env, 0.0, (disc[0], 1.01), np.random.default_rng(0),
                               samples=1024, max_distance=50.0)  # fmt: skip
    assert mask.all()  # a 2.5 mm pixel footprint: the 5 x 5 smoothing stays near the centre
    assert ratio[4, 4] == pytest.approx(0.5, abs=0.02)


def test_a_sun_at_the_zenith_casts_the_disc_straight_down():
    env = np.zeros((64, 128, 3), np.float32)
    env[1] = 100.0  # the row next to the zenith only (3 degrees from it)
    cam = look_at_camera(np.array([0.0, 8.0, 0.01]), np.array([0.0, 0.0, 0.0]), width=33, height=33)
    disc = (np.array([0.0, 1.5, 0.0]), 1.0)
    ratio, mask = shadow_ratio(_disc_test(*disc), cam, env, 0.0, (disc[0], 1.01), np.random.default_rng(1), samples=16)
    _, pts = ground_points(cam, 50.0)
    r = np.hypot(pts[..., 0], pts[..., 2])
    assert mask.all()
    assert ratio[r < 0.6].max() < 0.05  # inside the shadow (the 5 x 5 smoothing reaches 0.3 m here)
    assert ratio[r > 1.5].min() > 0.95  # outside


def test_camera_height_is_drawn_above_the_ground_and_aimed_at_the_people():
    pts = np.random.default_rng(0).normal(size=(200, 3)) * [0.2, 0.45, 0.15] + [0.0, 0.9, 0.0]
    cfg = CameraConfig(width=64, height=64, rare_rate=0.0, truncation_rate=0.0, height_m=(1.5, 1.9))
    for seed in range(10):
        cam, info = sample_camera(pts, cfg, np.random.default_rng(seed))
        eye = -cam.R.T @ cam.t
        assert 1.5 <= eye[1] <= 1.9 and info["height_m"] == pytest.approx(eye[1])
    off = CameraConfig(width=64, height=64, rare_rate=0.0, truncation_rate=0.0, height_m=())
    cam, info = sample_camera(pts, off, np.random.default_rng(3))
    assert "height_m" not in info and -10.0 <= info["elevation_deg"] <= 30.0
    with pytest.raises(ValueError, match="height_m must be"):
        CameraConfig(height_m=(2.0, 1.0))


def test_circle_of_confusion_of_a_thin_lens_by_hand():
    from synth.lens import circle_of_confusion

    # 50 mm at f/2 (A = 25 mm), f_px = 500, focused at 5 m: at infinity c = A f_px / s = 2.5 px;
    # at 2.5 m, |1/5 - 1/2.5| = 0.2 -> 2.5 px; in focus 0.
    c = circle_of_confusion(np.array([np.inf, 2.5, 5.0, 10.0]), 5.0, 500.0, 0.025)
    np.testing.assert_allclose(c, [2.5, 2.5, 0.0, 1.25])


def test_defocus_is_the_identity_in_focus_and_a_disc_convolution_at_constant_blur():
    from scipy.ndimage import convolve

    from synth.lens import defocus, disc_kernel

    img = np.random.default_rng(0).random((24, 30, 3)).astype(np.float32)
    np.testing.assert_array_equal(defocus(img, np.zeros((24, 30))), img)
    k = disc_kernel(6.0)
    assert k.sum() == pytest.approx(1.0) and k.shape == (7, 7)
    want = np.stack([convolve(img[..., c], k, mode="nearest") for c in range(3)], -1)
    np.testing.assert_allclose(defocus(img, np.full((24, 30), 6.0)), want, atol=1e-6)
    # Between two levels, the blend of both.
    half = defocus(img, np.full((24, 30), 5.0))
    four = np.stack([convolve(img[..., c], disc_kernel(4.0), mode="nearest") for c in range(3)], -1)
    np.testing.assert_allclose(half, 0.5 * (four + want), atol=1e-6)


def test_backdrop_takes_one_ray_a_pixel_while_pixels_are_smaller_than_texels():
    from synth.ground import backdrop_supersampling, env_backdrop

    rng = np.random.default_rng(0)
    env = rng.uniform(0.0, 2.0, (128, 256, 3)).astype(np.float32)  # 1.4 degrees a texel
    def cam(f):
        c = look_at_camera(np.array([0.0, 1.7, 4.0]), np.array([0.0, 1.0, 0.0]), width=48, height=48)
        return Camera(K=np.array([[f, 0, 24.0], [0, f, 24.0], [0, 0, 1]]), R=c.R, t=c.t, width=48, height=48)
    tele, wide = cam(400.0), cam(15.0)  # 0.14 and 2.4 degrees a pixel at the centre
    assert backdrop_supersampling(tele, 256) == 1
    assert backdrop_supersampling(wide, 256) == 2
    assert backdrop_supersampling(cam(45.0), 256) == 1  # 1.17 degrees, under a texel
    # Magnified, one bilinear lookup is the pixel's average: 4 x 4 rays change it by little.
    a, b = env_backdrop(tele, env, 0.2, 1.0), env_backdrop(tele, env, 0.2, 1.0, supersample=4)
    assert np.abs(a - b).mean() < 0.02 * b.mean()
    # Minified, one ray a pixel aliases; the chosen count is close to a dense average.
    dense = env_backdrop(wide, env, 0.2, 1.0, supersample=8)
    auto, one = env_backdrop(wide, env, 0.2, 1.0), env_backdrop(wide, env, 0.2, 1.0, supersample=1)
    assert np.abs(auto - dense).mean() < 0.5 * np.abs(one - dense).mean()


def test_the_scene_occluders_one_kernel_estimate_is_the_numpy_estimate():
    """SceneOccluder.blocked (the pooled estimate in one Dr.Jit kernel, what the generator uses)
    against the NumPy estimate around the same scene's ray test: a disc of radius 1 at height 1 in
    a uniform sky blocks half the cosine-weighted hemisphere straight under its centre."""
    from blsm.mitsuba_util import load_mitsuba, resolve_variant
    from synth.ground import SceneOccluder

    mi = load_mitsuba(resolve_variant(None))
    to_world = mi.ScalarTransform4f().translate([0.0, 1.0, 0.0]) @ mi.ScalarTransform4f().rotate([1.0, 0.0, 0.0], -90.0)
    occluder = SceneOccluder(mi, mi.load_dict({"type": "scene", "disc": {"type": "disk", "to_world": to_world}}))
    env = np.ones((64, 128, 3), np.float32)
    cam = look_at_camera(np.array([0.0, 4.0, 2.5]), np.array([0.0, 0.0, 0.0]), width=24, height=24)
    sphere = (np.array([0.0, 1.0, 0.0]), 1.01)
    kernel, mask = shadow_ratio(occluder, cam, env, 0.0, sphere, np.random.default_rng(0), samples=256)
    numpy_, mask2 = shadow_ratio(lambda o, d: occluder(o, d), cam, env, 0.0, sphere, np.random.default_rng(0), samples=256)
    assert mask.all() and np.array_equal(mask, mask2)
    assert np.abs(kernel - numpy_).max() < 0.05  # two Monte Carlo estimates (25 x 256 rays a pixel)
    assert kernel.min() == pytest.approx(0.5, abs=0.05) and numpy_.min() == pytest.approx(0.5, abs=0.05)
    assert kernel.max() > 0.85 and numpy_.max() > 0.85  # the shadow fades away from the disc
    again, _ = shadow_ratio(occluder, cam, env, 0.0, sphere, np.random.default_rng(0), samples=256)
    assert np.array_equal(kernel, again)  # the seed fixes it


def test_the_emitter_backdrop_is_the_numpy_backdrop():
    """synth.ground.emitter_backdrop (Mitsuba's envmap evaluated in one kernel, what the generator
    uses) against env_backdrop (NumPy, which follows Mitsuba's lookup) on a random map, rotated and
    scaled, with one and with 2 x 2 rays a pixel."""
    from blsm.mitsuba_util import load_mitsuba, resolve_variant
    from synth.ground import emitter_backdrop, env_backdrop

    mi = load_mitsuba(resolve_variant(None))
    env = np.random.default_rng(3).uniform(0.0, 2.0, (64, 128, 3)).astype(np.float32)
    rot, scale = 0.7, 1.6
    c, s = np.cos(rot), np.sin(rot)
    to_world = mi.ScalarTransform4f(np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1]]))
    scene = mi.load_dict({"type": "scene", "env": {"type": "envmap", "bitmap": mi.Bitmap(env), "scale": scale,
                                                   "to_world": to_world}})
    base = look_at_camera(np.array([0.3, 1.6, 4.0]), np.array([0.0, 1.0, 0.0]), width=40, height=30)
    cam = Camera(K=np.array([[30.0, 0.0, 21.0], [0.0, 32.0, 14.5], [0.0, 0.0, 1.0]]), R=base.R, t=base.t, width=40, height=30)
    for ss in (1, 2):
        want = env_backdrop(cam, env, rot, scale, supersample=ss)
        got = emitter_backdrop(mi, scene.environment(), cam, ss)
        assert got.shape == want.shape == (30, 40, 3)
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)  # float32 directions here, float64 there
    assert np.abs(emitter_backdrop(mi, scene.environment(), cam, 1) - env_backdrop(cam, env, rot + 0.3, scale, 1)).max() > 0.1
