"""``background.kind: default``: the embedded procedural sky, drawn per image (no files)."""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from synth.backgrounds.base import LUMA, MEAN_LUMINANCE, Background


@functools.lru_cache(maxsize=4)
def _directions(width: int) -> tuple[np.ndarray, np.ndarray]:
    """(width / 2, width, 3) float32 unit directions of a lat-long map's texel centres (Y up, row 0
    at the zenith) and (width / 2, 1) float32 ``sin(theta)`` solid-angle weights of the rows."""
    h = width // 2
    theta = (np.arange(h) + 0.5) / h * math.pi  # 0 at the zenith
    phi = (np.arange(width) + 0.5) / width * 2 * math.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(th) * np.sin(ph), np.cos(th), np.sin(th) * np.cos(ph)], axis=-1).astype(np.float32)
    w = np.sin(theta)[:, None].astype(np.float32)
    d.flags.writeable = w.flags.writeable = False  # cached: shared by every call
    return d, w


def procedural_sky(width: int, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """An embedded environment: sky gradient, sun disk and glow, coloured ground; mean luminance ``MEAN_LUMINANCE``.

    Returns:
        (width / 2, width, 3) float32 linear RGB and the parameters drawn.
    """
    d, theta_w = _directions(width)
    sun_el = math.radians(rng.uniform(15.0, 75.0))
    sun_az = rng.uniform(0.0, 2 * math.pi)
    sun = np.array([math.cos(sun_el) * math.sin(sun_az), math.sin(sun_el), math.cos(sun_el) * math.cos(sun_az)])
    zenith = np.array([0.25, 0.45, 0.95]) * rng.uniform(0.6, 1.2)
    horizon = np.array([0.85, 0.9, 1.0]) * rng.uniform(0.8, 1.2)
    ground = np.array([rng.uniform(0.15, 0.45), rng.uniform(0.15, 0.4), rng.uniform(0.1, 0.35)])
    sun_strength = rng.uniform(20.0, 80.0)
    f32 = np.float32
    # Rows run from the zenith down, so the sky is the first `n_sky` rows and the ground the rest;
    # only the sky rows are evaluated (the same arithmetic per texel as a full-map evaluation).
    n_sky = int((d[:, 0, 1] >= 0).sum())
    ds = d[:n_sky]
    up = np.sqrt(np.clip(ds[..., 1:2], 0.0, 1.0))
    sky = horizon.astype(f32) + (zenith - horizon).astype(f32) * up
    cos_sun = np.clip(ds @ sun.astype(f32), -1.0, 1.0)[..., None]
    glow = f32(sun_strength) * (cos_sun > math.cos(math.radians(2.5))) + f32(0.6) * np.exp((cos_sun - 1) * 12)
    sky += np.array([1.0, 0.9, 0.75], f32) * glow
    env = np.empty(d.shape, f32)
    env[:n_sky] = sky
    env[n_sky:] = (ground * (1.0 + 0.2 * sun[1])).astype(f32)
    mean = float(((env @ LUMA) * theta_w).sum(dtype=np.float64) / (theta_w.sum(dtype=np.float64) * width))
    params = {"sun_elevation_deg": math.degrees(sun_el), "sun_azimuth_deg": math.degrees(sun_az)}
    return (env * f32(MEAN_LUMINANCE / mean)).astype(np.float32), params


class Sky:
    """The kind ``default`` (:class:`synth.backgrounds.base.BackgroundKind`)."""

    name, needs_folder, follows_cameras = "default", False, True

    def check(self, cfg: Any) -> None:
        pass

    def open(self, cfg: Any) -> None:
        return None

    def draw(self, state: None, cfg: Any, rng: np.random.Generator, camera: Any, size: tuple[int, int],
             rotation: float, scale: float) -> Background:
        env, info = procedural_sky(cfg.env_width, rng)
        return Background("default", env, rotation, scale, None, {"rotation": rotation, "exposure": scale, **info})

    def records(self, cfg: Any) -> set[str]:
        return set()
