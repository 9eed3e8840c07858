"""The renderer's speed measures keep the pixels: shape-group layout vs meshes in the scene, the
spare emitter, texture uploads skipped for a slot that keeps its texture, and rendering only the
people's window."""

from __future__ import annotations

import gc

import numpy as np
import pytest
import torch

from blsm.camera import look_at_camera
from synth.render import PeopleRenderer, RenderMesh

SIZE = 40


@pytest.fixture(scope="module")
def scene(model):
    with torch.no_grad():
        out = model(pose=0.2 * torch.randn(1, 47, generator=torch.Generator().manual_seed(3)))
    verts = out.vertices[0].numpy().astype(np.float32)
    mesh = RenderMesh.build(model.faces.numpy(), model.uvs.numpy(), model.faces_uv.numpy())
    rng = np.random.default_rng(0)
    textures = [rng.uniform(0.1, 0.9, (64, 64, 3)).astype(np.float32) for _ in range(2)]
    env = np.ones((16, 32, 3), np.float32) * np.linspace(0.2, 1.0, 32, dtype=np.float32)[None, :, None]
    centre = 0.5 * (verts.min(0) + verts.max(0))
    cam = look_at_camera(centre + np.array([0.4, 0.2, 3.0]), centre, width=SIZE, height=SIZE)
    return verts, mesh, textures, env, cam


def _renderer(scene, **kw) -> PeopleRenderer:
    verts, mesh, textures, env, cam = scene
    return PeopleRenderer([mesh], [textures[0].shape[:2]], SIZE, SIZE, env_shape=env.shape[:2], **kw)


def _frame(r: PeopleRenderer, scene, texture: int = 0, seed: int = 1):
    verts, mesh, textures, env, cam = scene
    return r.render([verts], [textures[texture]], cam, env, 0.3, 1.0, spp=4, seed=seed)


def _assert_same(a, b, rgb_atol: float = 0.0) -> None:
    assert np.array_equal(a.hit, b.hit) and np.array_equal(a.face, b.face)
    assert np.array_equal(a.position, b.position)
    assert np.abs(a.rgb - b.rgb).max() <= rgb_atol


def test_shape_group_layout_gives_the_plain_layouts_pixels(scene):
    """Each person in a shape group seen through an identity instance (faster BVH rebuilds) gives
    the plain layout's labels exactly. The image agrees but for a few pixels where a light path
    took another turn (Monte Carlo noise: the instance's intersection offsets differ slightly)."""
    grouped, plain = _frame(_renderer(scene), scene), _frame(_renderer(scene, instanced=False), scene)
    assert grouped.hit.sum() > 100  # the person is in view
    _assert_same(grouped, plain, rgb_atol=np.inf)
    differ = np.abs(grouped.rgb - plain.rgb).max(-1) > 1e-5
    assert differ.mean() < 0.02, f"{differ.sum()} of {differ.size} pixels differ"
    assert abs(float(grouped.rgb.mean() - plain.rgb.mean())) < 1e-3


def test_the_spare_emitter_does_not_change_the_image(scene):
    r = _renderer(scene)
    with_spare = _frame(r, scene)
    r.spare_emitter = None
    gc.collect()
    _assert_same(with_spare, _frame(r, scene))


def test_a_slot_shows_its_current_texture_after_switching(scene):
    """Texture uploads are skipped while a slot keeps the same array; switching back and forth
    shows each texture as a fresh renderer does."""
    r = _renderer(scene)
    first, second, third = (_frame(r, scene, texture=t) for t in (0, 1, 0))
    assert np.abs(first.rgb - second.rgb).max() > 0.05  # the textures do show
    fresh = _frame(_renderer(scene), scene, texture=1)
    _assert_same(second, fresh, rgb_atol=1e-3)
    _assert_same(third, first, rgb_atol=1e-3)


def test_multijitter_sampler_has_less_noise_and_the_same_labels(scene):
    """render.sampler: at equal samples per pixel a multi-jittered sampler is closer to a
    high-sample reference than the independent one; the label pass does not depend on it."""
    verts, mesh, textures, env, cam = scene
    ref = _renderer(scene).render([verts], [textures[0]], cam, env, 0.3, 1.0, spp=1024, seed=7)
    err = {}
    frames = {}
    for sampler in ("independent", "multijitter"):
        r = _renderer(scene, sampler=sampler)
        errs = []
        for seed in (1, 2, 3):
            f = r.render([verts], [textures[0]], cam, env, 0.3, 1.0, spp=16, seed=seed)
            errs.append(float(np.mean((f.rgb - ref.rgb) ** 2)))
        err[sampler], frames[sampler] = np.mean(errs), f
    assert err["multijitter"] < 0.7 * err["independent"], err
    _assert_same(frames["multijitter"], frames["independent"], rgb_atol=np.inf)


def test_people_window_holds_the_projected_mesh_and_rounds_its_sides():
    from synth.render import people_window

    cam = look_at_camera(np.array([0.0, 1.0, 4.0]), np.array([0.0, 1.0, 0.0]), width=64, height=48)
    pts = np.array([[-0.3, 0.6, 0.0], [0.2, 1.5, 0.1], [0.0, 1.0, -0.2]])
    x0, y0, w, h = people_window(cam, pts, quantum=16)
    uv = cam.project(pts)
    assert x0 <= uv[:, 0].min() and uv[:, 0].max() < x0 + w and y0 <= uv[:, 1].min() and uv[:, 1].max() < y0 + h
    assert w % 16 == 0 and h % 16 == 0 and x0 + w <= 64 and y0 + h <= 48
    assert people_window(cam, pts, quantum=1, margin=0) == (
        int(np.floor(uv[:, 0].min())), int(np.floor(uv[:, 1].min())),
        int(np.floor(uv[:, 0].max())) - int(np.floor(uv[:, 0].min())) + 1,
        int(np.floor(uv[:, 1].max())) - int(np.floor(uv[:, 1].min())) + 1)  # fmt: skip
    assert people_window(cam, pts * 40.0, quantum=16) == (0, 0, 64, 48)  # larger than the image: all of it
    behind = np.concatenate([pts, [[0.0, 1.0, 5.0]]])  # a point behind the camera: the whole image
    assert people_window(cam, behind) == (0, 0, 64, 48)


def test_a_window_render_is_the_full_render_where_people_can_be(scene):
    """With the environment hidden, rendering only the people's window gives the full render's
    labels exactly, nothing outside the window (where the full render has no person either), and
    inside it the same image up to Monte Carlo noise."""
    from synth.render import people_window

    verts, mesh, textures, env, cam = scene
    r = _renderer(scene, backplate=True)
    window = people_window(cam, verts, quantum=2)
    x0, y0, w, h = window
    assert w * h < 0.8 * SIZE * SIZE, window  # a real crop
    inside = np.zeros((SIZE, SIZE), bool)
    inside[y0 : y0 + h, x0 : x0 + w] = True
    full = r.render([verts], [textures[0]], cam, env, 0.3, 1.0, spp=256, seed=1)
    part = r.render([verts], [textures[0]], cam, env, 0.3, 1.0, spp=256, seed=1, window=window)
    _assert_same(part, full, rgb_atol=np.inf)
    assert full.alpha[~inside].max() == 0.0 and not full.hit[~inside].any()
    assert part.alpha[~inside].max() == 0.0 and part.rgb[~inside].max() == 0.0
    assert full.alpha.sum() > 50
    assert np.abs(part.alpha - full.alpha).max() < 0.15
    assert abs(float(part.rgb.mean() - full.rgb.mean())) < 2e-3
    assert float(np.sqrt(np.mean((part.rgb - full.rgb) ** 2))) < 0.02
    with pytest.raises(ValueError, match="environment hidden"):
        _renderer(scene).render([verts], [textures[0]], cam, env, 0.3, 1.0, spp=1, window=window)
    with pytest.raises(ValueError, match="not inside"):
        r.render([verts], [textures[0]], cam, env, 0.3, 1.0, spp=1, window=(SIZE - 4, 0, 8, 8))


@pytest.mark.parametrize("denoise", [False, True])
def test_trace_window_over_the_whole_image_is_mi_render(scene, denoise):
    """synth.render.trace_window over the whole image draws mi.render's samples (same seed, same
    wavefront order): the same film channels (RGBA, and albedo and normal with the AOV integrator
    the denoiser reads) up to the order of the per-pixel sums; a window is that image's crop up
    to Monte Carlo noise (its own random stream) and costs no new kernel."""
    import drjit as dr

    from synth.render import trace_window

    verts, mesh, textures, env, cam = scene
    r = _renderer(scene, backplate=True, denoise=denoise, sampler="multijitter")
    r.render([verts], [textures[0]], cam, env, 0.3, 1.0, spp=16, seed=5)  # the scene as a frame leaves it
    mi, sensor, integ = r.mi, r.scene.sensors()[0], r.scene.integrator()
    ref = np.asarray(mi.TensorXf(mi.render(r.scene, sensor=sensor, spp=16, seed=9)))
    got = trace_window(mi, r.scene, sensor, integ, (0, 0, SIZE, SIZE), 16, 9)
    assert got.shape == ref.shape == (SIZE, SIZE, 10 if denoise else 4)
    assert ref[..., 3].sum() > 100  # the person is in view
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-6)
    other = trace_window(mi, r.scene, sensor, integ, (0, 0, SIZE, SIZE), 16, 10)
    assert np.abs(other - ref).max() > 1e-3  # another seed, other samples
    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        part = trace_window(mi, r.scene, sensor, integ, (7, 5, 21, 30), 16, 9)
        history = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was)
    assert part.shape == (30, 21, ref.shape[2])
    assert all(k["cache_hit"] for k in history if k["type"] == dr.KernelType.JIT)
    assert abs(float(part[..., 3].mean() - ref[5:35, 7:28, 3].mean())) < 0.05
