"""A ground that receives the people's shadows: the shadow catcher, and the backdrop it darkens.

The people stand on the plane ``y = 0`` (:mod:`synth.generate` puts every person's lowest vertex on
it). Behind them the image shows a backdrop -- the environment map seen in the camera's directions
(HDRI or procedural sky) or a backplate photograph -- that has no people in it, so nothing there
darkens under them: they float. The shadow catcher puts the missing shadows onto the backdrop:

1. The pixel-centre ray of every pixel that looks down (and is not covered by a person) meets the
   ground plane at a point ``x``, up to ``max_distance`` metres away.
2. The unoccluded irradiance of a horizontal diffuse ground under a distant environment ``L`` is
   ``E = int_{y > 0} L(w) cos(theta) dw``, the same at every point. With the people in the scene a
   point receives ``E_x = int V(x, w) L(w) cos(theta) dw``, ``V`` the visibility. The shadow ratio
   ``S(x) = E_x / E`` is estimated with ``samples`` directions drawn with density proportional to
   ``L(w) cos(theta)`` over the upper hemisphere (importance sampling of the environment map's
   texels, so a sun's sharp shadow and the sky's soft contact shadow are both found):
   ``S(x) = (1/n) sum_i V(x, w_i)``. The directions are drawn once per image (a pool of 8192)
   and every ground point takes its ``n`` from the pool at random, which costs a fraction of
   drawing ``n`` fresh directions for every point. Rays that miss the people's bounding sphere are unoccluded and
   are not traced; the others are tested against the people's meshes with Mitsuba's
   ``Scene.ray_test`` (the renderer's own scene, so the people are exactly the rendered ones). On a
   Mitsuba scene (:class:`SceneOccluder`) the picking, the sphere test, the ray test and the
   per-point sums are one Dr.Jit kernel.
3. ``S`` is smoothed by a normalised 5 x 5 box filter over ground pixels (Monte Carlo noise),
   and the backdrop is multiplied by it on ground pixels: a photographed diffuse ground under a
   shadow is darker by exactly that ratio. The people are composited over the result with the
   render's anti-aliased coverage.

Assumptions (docs/realism.md): the ground is flat, diffuse and at ``y = 0``; an HDRI's own ground
is taken to be that plane (HDRIs are shot about 1.7 m above the ground, so the camera height is
sampled around it, :class:`synth.camera.CameraConfig` ``height_m``); a backplate's horizon is not
known, so its ground is where the plane projects with the sampled camera. The shadow darkens the
backdrop only; the people are lit by the full environment as before (no bounce light from the
ground). Labels are unaffected: the ground is not a person, so masks, parts, depth and keypoints
are those of the people alone.

The environment lookups follow Mitsuba's ``envmap`` exactly (lat-long, ``u = atan2(x, -z) / 2 pi``,
``v = acos(y) / pi``, bilinear with rows from the zenith to the nadir, ``to_world`` the rotation about +Y of
:func:`blsm.mitsuba_util.env_rotation`, which the renderer gives the envmap too), so the
backdrop matches what the path tracer showed before (``tests/synth/test_ground.py`` compares).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.ndimage import uniform_filter

from blsm.camera import Camera
from blsm.mitsuba_util import env_rotation

_LUMA = np.array([0.2126, 0.7152, 0.0722])


def env_lookup(env: np.ndarray, directions: np.ndarray, rotation: float = 0.0, scale: float = 1.0) -> np.ndarray:
    """Radiance (N, 3) of a lat-long map ``env`` (H, W, 3) in world ``directions`` (N, 3), as
    Mitsuba's ``envmap`` with ``to_world`` a rotation by ``rotation`` about +Y and ``scale``."""
    d = np.asarray(directions, np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    v = d @ env_rotation(rotation)  # to_world^-1 applied to row vectors: R^T d
    h, w = env.shape[:2]
    u = np.arctan2(v[:, 0], -v[:, 2]) / (2.0 * math.pi)
    u -= np.floor(u)
    t = np.arccos(np.clip(v[:, 1], -1.0, 1.0)) / math.pi
    # Bilinear: texel columns centred at (i + 0.5) / W, wrapping around; rows at i / (H - 1), the
    # first at the zenith and the last at the nadir (what Mitsuba's envmap does; checked to 1e-5).
    x, y = u * w - 0.5, t * (h - 1)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    xa, xb = x0 % w, (x0 + 1) % w
    ya, yb = np.clip(y0, 0, h - 1), np.clip(y0 + 1, 0, h - 1)
    e = env.reshape(h * w, -1)  # gathered texels only are widened (no copy of the whole map)

    def texel(r: np.ndarray, c: np.ndarray) -> np.ndarray:
        return e[r * w + c].astype(np.float64)

    out = (texel(ya, xa) * (1 - fx) + texel(ya, xb) * fx) * (1 - fy) + (texel(yb, xa) * (1 - fx) + texel(yb, xb) * fx) * fy
    return (out * scale).astype(np.float32)


_RAYS_CACHE: list[tuple[bytes, tuple[np.ndarray, np.ndarray]]] = []  # the last call's (key, rays)


def pixel_rays(camera: Camera, offsets: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Camera centre (3,) and unit world directions (H, W, S, 3) of rays through each pixel at the
    sub-pixel ``offsets`` (S, 2) in [0, 1) (default: the centre, 0.5). Read-only arrays: the last
    call's are kept, since the backdrop and the ground points of one image ask for the same rays."""
    offsets = np.array([[0.5, 0.5]]) if offsets is None else np.asarray(offsets, np.float64)
    key = b"".join(np.ascontiguousarray(a, np.float64).tobytes() for a in (camera.K, camera.R, camera.t, offsets))
    key += np.array([camera.width, camera.height, *offsets.shape]).tobytes()
    if _RAYS_CACHE and _RAYS_CACHE[0][0] == key:
        return _RAYS_CACHE[0][1]
    u = np.arange(camera.width)[None, :, None] + offsets[None, None, :, 0]
    v = np.arange(camera.height)[:, None, None] + offsets[None, None, :, 1]
    u, v = np.broadcast_arrays(u, v)
    pix = np.stack([u, v, np.ones_like(u)], axis=-1)  # (H, W, S, 3)
    cam_dirs = pix @ np.linalg.inv(camera.K).T
    world = cam_dirs @ camera.R  # R^T d for row vectors
    world /= np.linalg.norm(world, axis=-1, keepdims=True)
    centre = -camera.R.T @ camera.t
    centre.flags.writeable = world.flags.writeable = False
    _RAYS_CACHE[:] = [(key, (centre, world))]
    return centre, world


def backdrop_supersampling(camera: Camera, env_width: int) -> int:
    """Rays per pixel side that :func:`env_backdrop` needs: 1 while a pixel spans no more than one
    texel of the lat-long map (the bilinear lookup is then already the pixel's average, as for
    the training sets' 192 px views of 1K maps), else enough that each ray steps about a texel."""
    pixel = 2.0 * math.atan(0.5 * camera.width / float(camera.K[0, 0])) / camera.width  # radians, at the centre
    texel = 2.0 * math.pi / env_width
    return int(min(4, max(1, math.ceil(pixel / texel - 1e-9))))


def env_backdrop(camera: Camera, env: np.ndarray, rotation: float, scale: float, supersample: int | None = None) -> np.ndarray:
    """(H, W, 3) the environment as a camera sees it, ``supersample``^2 stratified rays a pixel
    (None: :func:`backdrop_supersampling`)."""
    s = backdrop_supersampling(camera, env.shape[1]) if supersample is None else supersample
    g = (np.arange(s) + 0.5) / s
    offsets = np.stack(np.meshgrid(g, g, indexing="xy"), axis=-1).reshape(-1, 2)
    _, dirs = pixel_rays(camera, offsets)
    h, w = camera.height, camera.width
    rad = env_lookup(env, dirs.reshape(-1, 3), rotation, scale).reshape(h, w, s * s, 3)
    return rad.mean(axis=2)


def emitter_backdrop(mi: Any, emitter: Any, camera: Camera, supersample: int) -> np.ndarray:
    """(H, W, 3) what :func:`env_backdrop` computes, evaluated by the scene's own environment
    ``emitter`` (Mitsuba's ``envmap``, with the image's map, rotation and scale already set) in
    Dr.Jit: the same ``supersample``^2 stratified rays a pixel, the same radiance the path tracer's
    escaped rays see. The camera and the sub-pixel offsets enter as data, one launch per offset, so
    no camera or supersampling count compiles a kernel; the pixel directions are float32 here
    (NumPy's are float64), which moves a value by about 1e-5 of it."""
    import drjit as dr

    w, h, s = camera.width, camera.height, int(supersample)
    m = (camera.R.T @ np.linalg.inv(camera.K)).astype(np.float32)  # pixel (u, v, 1) -> world direction
    mo = [dr.opaque(mi.Float, float(x)) for x in m.reshape(-1)]
    pixel, cols = dr.arange(mi.UInt32, w * h), dr.opaque(mi.UInt32, w)
    row = pixel // cols
    col = mi.Float(pixel - row * cols)
    row = mi.Float(row)
    total = np.zeros((h * w, 3), np.float64)
    for k in range(s * s):
        u = col + dr.opaque(mi.Float, (k % s + 0.5) / s)
        v = row + dr.opaque(mi.Float, (k // s + 0.5) / s)
        d = mi.Vector3f(mo[0] * u + mo[1] * v + mo[2], mo[3] * u + mo[4] * v + mo[5], mo[6] * u + mo[7] * v + mo[8])
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wi = -dr.normalize(d)
        total += np.asarray(mi.TensorXf(dr.ravel(emitter.eval(si)), shape=(h * w, 3)))
    return (total / (s * s)).astype(np.float32).reshape(h, w, 3)


_CDF_CACHE: list[tuple[np.ndarray, np.ndarray]] = []  # (env, its cdf), the last few environments


def _env_cdf(env: np.ndarray) -> np.ndarray:
    """The cumulative ``L cos(theta) sin(theta)`` of the upper hemisphere's texels (row-major),
    normalised; kept for the last 8 environment arrays (a generator shows a few HDRIs again and
    again, and never changes one in place)."""
    for e, cdf in _CDF_CACHE:
        if e is env:
            return cdf
    h = env.shape[0]
    theta = np.arange(h) / (h - 1) * math.pi  # row i looks at theta_i (env_lookup)
    rows = np.flatnonzero(np.cos(theta) > 0.0)  # the upper hemisphere; the rest weigh 0
    lum = np.maximum(env[rows].astype(np.float64) @ _LUMA, 0.0)
    weight = np.zeros(env.shape[:2])
    weight[rows] = lum * (np.cos(theta[rows]) * np.sin(theta[rows]))[:, None]  # texel solid angle ~ sin(theta)
    total = weight.sum()
    if not total > 0:
        raise ValueError("the environment has no light above the horizon")
    cdf = np.cumsum(weight.ravel()) / total
    _CDF_CACHE.append((env, cdf))
    del _CDF_CACHE[:-8]
    return cdf


@dataclass
class EnvSampler:
    """Directions drawn with density proportional to ``L(w) cos(theta)`` over the upper hemisphere
    of a lat-long map (luminance ``L``); see the module docstring."""

    env: np.ndarray
    rotation: float

    def __post_init__(self) -> None:
        self._cdf = _env_cdf(self.env)
        self._shape = self.env.shape[:2]

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, 3) unit world directions, all with y > 0."""
        h, w = self._shape
        idx = np.minimum(np.searchsorted(self._cdf, rng.uniform(size=n), side="right"), h * w - 1)
        row, col = np.divmod(idx, w)
        # Uniform in the texel's footprint around its direction; y > 0 is kept below.
        t = np.clip((row + rng.uniform(size=n) - 0.5) / (h - 1), 0.0, 1.0) * math.pi
        u = (col + rng.uniform(size=n)) / w
        phi = u * 2.0 * math.pi  # atan2(x, -z) = phi
        local = np.stack([np.sin(t) * np.sin(phi), np.cos(t), -np.sin(t) * np.cos(phi)], axis=-1)
        local[:, 1] = np.maximum(local[:, 1], 1e-4)
        world = local @ env_rotation(self.rotation).T
        return world / np.linalg.norm(world, axis=-1, keepdims=True)


def ground_points(camera: Camera, max_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel-centre ray meets ``y = 0``: a (H, W) mask of rays that do within
    ``max_distance`` of the camera (horizontally), and the (H, W, 3) points (0 elsewhere)."""
    centre, dirs = pixel_rays(camera)
    dirs = dirs[:, :, 0]
    if centre[1] <= 0.0:
        return np.zeros(dirs.shape[:2], bool), np.zeros(dirs.shape, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -centre[1] / dirs[..., 1]
    pts = centre + t[..., None] * dirs
    horiz = np.linalg.norm((pts - centre)[..., [0, 2]], axis=-1)
    mask = (dirs[..., 1] < -1e-6) & (horiz <= max_distance)
    pts[~mask] = 0.0
    return mask, pts


def shadow_ratio(
    ray_test: Any,
    camera: Camera,
    env: np.ndarray,
    rotation: float,
    people_sphere: tuple[np.ndarray, float],
    rng: np.random.Generator,
    samples: int = 32,
    max_distance: float = 60.0,
    exclude: np.ndarray | None = None,
    pool: int = 8192,
) -> tuple[np.ndarray, np.ndarray]:
    """The shadow ratio ``S`` (H, W) in [0, 1] on the ground (1 elsewhere), and the ground mask.

    Args:
        ray_test: ``f(origins (N, 3), directions (N, 3)) -> (N,) bool``, True where a ray hits a
            person (:func:`mitsuba_ray_test`).
        people_sphere: centre and radius of a sphere around every person (rays missing it are free).
        exclude: (H, W) bool pixels to skip (those a person covers).
        pool: the directions are drawn once per image, ``pool`` of them with density
            ``L cos``; each ground pixel takes ``samples`` of them uniformly at random (a
            resampling of that discrete estimate of the environment, so ``S`` stays an unbiased
            estimate of the pool's shadow; 0: every ray draws its own direction, slower).
    """
    mask, pts = ground_points(camera, max_distance)
    if exclude is not None:
        mask &= ~exclude
    ratio = np.ones(mask.shape, np.float64)
    if not mask.any():
        return ratio.astype(np.float32), mask
    origins = pts[mask] + np.array([0.0, 1e-4, 0.0])  # (P, 3), just above the ground
    sampler = EnvSampler(env, rotation)
    if pool and isinstance(ray_test, SceneOccluder):
        blocked = ray_test.blocked(origins, sampler.sample(pool, rng), samples, people_sphere, int(rng.integers(2**63)))
    else:
        blocked = _blocked(ray_test, origins, sampler, samples, people_sphere, rng, pool)
    ratio[mask] = 1.0 - np.asarray(blocked, np.float64) / samples
    # Smooth the Monte Carlo noise over ground pixels only (normalised box filter).
    m = mask.astype(np.float64)
    num = uniform_filter(ratio * m, size=5, mode="nearest")
    den = uniform_filter(m, size=5, mode="nearest")
    smooth = np.where(den > 0, num / np.maximum(den, 1e-12), 1.0)
    ratio[mask] = smooth[mask]
    return ratio.astype(np.float32), mask


def _blocked(ray_test: Any, origins: np.ndarray, sampler: EnvSampler, samples: int,
             people_sphere: tuple[np.ndarray, float], rng: np.random.Generator, pool: int) -> np.ndarray:
    """(P,) blocked rays of each origin, in NumPy around any ``ray_test`` (:func:`shadow_ratio`)."""
    p = len(origins)
    if pool:
        dirs = sampler.sample(pool, rng).astype(np.float32)[rng.integers(0, pool, size=(p, samples))]
    else:
        dirs = sampler.sample(p * samples, rng).astype(np.float32).reshape(p, samples, 3)
    # A ray o + t d (t > 0) can meet the sphere only where disc >= 0 and its far root is ahead.
    c, r = people_sphere
    oc = origins - c
    b = np.einsum("psk,pk->ps", dirs, oc.astype(np.float32))
    disc = b * b - ((oc * oc).sum(-1) - r * r).astype(np.float32)[:, None]
    cand = (disc >= 0) & (np.sqrt(np.maximum(disc, 0.0)) > b)
    pi, si = np.nonzero(cand)
    if not len(pi):
        return np.zeros(p)
    hit = np.asarray(ray_test(origins[pi], dirs[pi, si].astype(np.float64)), bool)
    return np.bincount(pi[hit], minlength=p)


class SceneOccluder:
    """The people of a loaded Mitsuba scene as the occluders of :func:`shadow_ratio`.

    Called as ``f(origins (N, 3), directions (N, 3)) -> (N,) bool`` it tests the given rays
    (``Scene.ray_test``). :meth:`blocked` does the whole pooled estimate in one Dr.Jit kernel:
    every ground point's ``samples`` directions are picked from the pool by a PCG32 stream per
    ray (seeded by ``seed``), the rays that miss the people's sphere are masked off, the rest are
    tested against the scene, and the blocked rays are summed per point; only the points and the
    pool go in and one count per point comes out (the NumPy path moves every ray's direction).
    """

    def __init__(self, mi: Any, scene: Any) -> None:
        self.mi, self.scene = mi, scene

    def _vec(self, a: np.ndarray, kind: Any) -> Any:
        """(N, 3) NumPy rows as a Dr.Jit ``kind`` (``Point3f``, ``Vector3f``) of N float32 entries."""
        return kind(*(np.ascontiguousarray(a[:, i], np.float32) for i in range(3)))

    def __call__(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        mi = self.mi
        ray = mi.Ray3f(self._vec(origins, mi.Point3f), self._vec(directions, mi.Vector3f))
        return np.asarray(self.scene.ray_test(ray), dtype=bool)

    def blocked(self, origins: np.ndarray, pool: np.ndarray, samples: int, people_sphere: tuple[np.ndarray, float],
                seed: int) -> np.ndarray:
        """(P,) how many of each origin's ``samples`` rays, directions drawn uniformly from ``pool``
        (M, 3), hit a person."""
        import drjit as dr

        mi = self.mi
        p, m = len(origins), len(pool)
        o_all, d_all = self._vec(origins, mi.Point3f), self._vec(pool, mi.Vector3f)
        idx = dr.arange(mi.UInt32, p * samples)
        point = idx // samples
        rng = mi.PCG32(size=p * samples, initstate=dr.opaque(mi.UInt64, seed % 2**64), initseq=mi.UInt64(idx))
        o = dr.gather(mi.Point3f, o_all, point)
        d = dr.gather(mi.Vector3f, d_all, rng.next_uint32_bounded(m))
        # A ray o + t d (t > 0) can meet the sphere only where disc >= 0 and its far root is ahead.
        # Opaque, so that a new sphere or seed does not compile a new kernel.
        c, r = people_sphere
        oc = o - dr.opaque(mi.Point3f, [float(x) for x in c])
        b = dr.dot(d, oc)
        disc = b * b - (dr.squared_norm(oc) - dr.opaque(mi.Float, float(r) ** 2))
        cand = (disc >= 0) & (dr.safe_sqrt(disc) > b)
        hit = self.scene.ray_test(mi.Ray3f(o, d), cand)
        return np.asarray(dr.block_sum(dr.select(hit & cand, 1.0, 0.0), samples), np.float64)


def mitsuba_ray_test(mi: Any, scene: Any) -> SceneOccluder:
    """The ``ray_test`` of :func:`shadow_ratio` for a loaded Mitsuba scene (its shapes occlude)."""
    return SceneOccluder(mi, scene)
