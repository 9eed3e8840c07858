"""Camera sampling for synthetic images: OpenCV pinhole cameras that frame a person.

Conventions (README): metres, Y up, the body faces +Z at rest; cameras are OpenCV pinholes (x right,
y down, z forward) with ``K`` (3, 3) and world-to-camera ``R``, ``t``; pixel centres are at integer
+ 0.5, so the principal point of a W x H image is (W / 2, H / 2).

A sample draws, from the sample's own random generator:

- the focal length as a full-frame-equivalent lens (36 mm sensor width), log-uniform in
  ``focal_mm``;
- the view: yaw uniform in ``yaw_deg`` about the person, elevation uniform in ``elevation_deg``, a
  small roll (normal, ``roll_sd_deg``); with probability ``frontal_rate`` (0 by default: no draw)
  the yaw is instead uniform in ``frontal_yaw_deg`` about the direction the first person faces, as
  photographs mostly show people from the front; with probability ``rare_rate`` a rare view instead:
  from above (elevation 55..85), from below (-50..-25) or upside down (roll 180), equally likely;
- with ``height_m`` (the default, 1.4 to 2.0 m) a normal or upside-down view instead places the camera
  at a height drawn uniformly there, above the ground ``y = 0`` the people stand on, and aims it at
  them: the elevation follows from the height and the distance. HDRIs are shot about 1.7 m above
  their ground, so the horizon and the people's size against the backdrop agree with it.
  ``height_m: []`` keeps the drawn elevation (the sampler before this option);
- with ``f_number`` ([low, high], off by default) an aperture, log-uniform in that range, for a
  thin lens focused on the people (:mod:`synth.lens`): ``info`` records ``f_number`` and
  ``focus_m``, and the generator blurs the backdrop by the lens' circle of confusion;
- the distance, so that the person's projected height fills ``fill`` of the image height;
- with probability ``truncation_rate``, a shifted principal point so that the person is partly out
  of frame (15 % to 50 % of the person's box beyond one image side, drawn uniformly); otherwise the
  whole person is in frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from blsm.camera import Camera, look_at_camera

SENSOR_WIDTH_MM = 36.0
MAX_IMAGE_SIDE = 8192
"""Pixels, either side of the image: beyond it Mitsuba's film and the label buffers of one image
take tens of GiB (see ``synth.config.render_memory_bytes``)."""


@dataclass(frozen=True)
class CameraConfig:
    """Ranges of the camera sampler (see the module docstring)."""

    width: int = 256
    height: int = 256
    focal_mm: tuple[float, float] = (28.0, 85.0)
    yaw_deg: tuple[float, float] = (-180.0, 180.0)
    elevation_deg: tuple[float, float] = (-10.0, 30.0)
    roll_sd_deg: float = 3.0
    rare_rate: float = 0.05
    fill: tuple[float, float] = (0.55, 0.9)
    truncation_rate: float = 0.1
    height_m: tuple[float, ...] = (1.4, 2.0)
    f_number: tuple[float, ...] = ()
    frontal_rate: float = 0.0
    frontal_yaw_deg: tuple[float, float] = (-45.0, 45.0)

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise ValueError(f"camera size must be positive, got {self.width}x{self.height}")
        if max(self.width, self.height) > MAX_IMAGE_SIDE:
            raise ValueError(
                f"camera size {self.width}x{self.height} is over the limit of {MAX_IMAGE_SIDE} px a side"
            )
        if not 0.0 <= self.frontal_rate <= 1.0:
            raise ValueError(f"camera frontal_rate must be in [0, 1], got {self.frontal_rate}")
        for name in ("focal_mm", "yaw_deg", "elevation_deg", "fill", "frontal_yaw_deg"):
            lo, hi = getattr(self, name)
            if not lo <= hi:
                raise ValueError(f"camera {name} must be [low, high], got {[lo, hi]}")
        if not 0 < self.focal_mm[0]:
            raise ValueError(f"camera focal_mm must be positive, got {list(self.focal_mm)}")
        if not (0 < self.fill[0] and self.fill[1] <= 1.5):
            raise ValueError(f"camera fill must be in (0, 1.5], got {list(self.fill)}")
        if not -90 < self.elevation_deg[0] <= self.elevation_deg[1] < 90:
            raise ValueError(f"camera elevation_deg must be inside (-90, 90), got {list(self.elevation_deg)}")
        if len(self.height_m) not in (0, 2) or (self.height_m and not 0.05 <= self.height_m[0] <= self.height_m[1]):
            raise ValueError(f"camera height_m must be [] or [low, high] metres with 0.05 <= low <= high, got {list(self.height_m)}")
        if len(self.f_number) not in (0, 2) or (self.f_number and not 0.5 <= self.f_number[0] <= self.f_number[1]):
            raise ValueError(f"camera f_number must be [] or [low, high] with 0.5 <= low <= high, got {list(self.f_number)}")
        for name in ("rare_rate", "truncation_rate"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"camera {name} must be in [0, 1], got {getattr(self, name)}")


def outline_index(points: np.ndarray) -> np.ndarray:
    """Indices of the points of ``points`` (N, 3) that lie on their convex hull (all of them when
    N < 64 or the hull is degenerate).

    Every linear function of the points (a depth, a bounding box) and every perspective projection
    of them onto an image, when all of them are in front of the camera, takes its extremes on these
    points, so framing and boxes computed from them equal those from all the points (a person's
    ~13k vertices have a few hundred hull vertices).
    """
    pts = np.asarray(points)
    if len(pts) < 64:
        return np.arange(len(pts))
    from scipy.spatial import ConvexHull, QhullError

    try:
        return ConvexHull(np.asarray(pts, dtype=np.float64)).vertices
    except (QhullError, ValueError):
        return np.arange(len(pts))


def _box(cam: Camera, points: np.ndarray) -> np.ndarray:
    uv = cam.project(points)
    return np.concatenate([uv.min(0), uv.max(0)])


def aimed_camera(eye: np.ndarray, target: np.ndarray, roll: float, focal_px: float, cfg: CameraConfig) -> Camera:
    """The camera at ``eye`` looking at ``target`` (world up +Y), rolled by ``roll`` radians about its
    optical axis, focal length ``focal_px`` pixels, principal point at the image centre."""
    cam = look_at_camera(eye, target, width=cfg.width, height=cfg.height)
    c, s = math.cos(roll), math.sin(roll)
    r_roll = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # about the optical axis
    k = np.array([[focal_px, 0.0, cfg.width / 2.0], [0.0, focal_px, cfg.height / 2.0], [0.0, 0.0, 1.0]])
    r = r_roll @ cam.R
    return Camera(K=k, R=r, t=-r @ eye, width=cfg.width, height=cfg.height)


def facing_yaw_deg(global_orient: np.ndarray) -> float:
    """The yaw (degrees about +Y; 0: +Z) of the direction a body with root rotation vector
    ``global_orient`` (3,) faces: its rest forward axis +Z, rotated, in the ground plane."""
    from scipy.spatial.transform import Rotation

    f = Rotation.from_rotvec(np.asarray(global_orient, np.float64)).apply([0.0, 0.0, 1.0])
    return math.degrees(math.atan2(f[0], f[2]))


def sample_camera(
    points: np.ndarray, cfg: CameraConfig, rng: np.random.Generator, roll_deg: float = 0.0,
    facing_deg: float = 0.0,
) -> tuple[Camera, dict[str, Any]]:
    """Sample a camera framing ``points`` (the person's vertices or keypoints, world metres);
    ``roll_deg`` is added to the drawn roll (a portrait camera's 90 degrees); ``facing_deg``: the
    yaw of the direction the first person faces (0: +Z, the rest pose's), the centre of
    ``frontal_yaw_deg``.

    Returns:
        The camera and a dict of what was drawn: ``view`` ("normal", "above", "below",
        "upside_down"), ``focal_mm``, ``yaw_deg``, ``elevation_deg``, ``roll_deg``, ``distance``,
        ``fill``, ``truncated`` (bool), ``truncation`` (fraction of the person's box beyond the
        image side ``truncation_side``).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2 or not np.isfinite(pts).all():
        raise ValueError(f"points must be a finite (N >= 2, 3) array, got shape {pts.shape}")
    pts = pts[outline_index(pts)]  # the same camera, from a few hundred points instead of thousands
    centre = 0.5 * (pts.min(0) + pts.max(0))
    f_mm = float(math.exp(rng.uniform(math.log(cfg.focal_mm[0]), math.log(cfg.focal_mm[1]))))
    f_px = f_mm / SENSOR_WIDTH_MM * cfg.width
    yaw = math.radians(rng.uniform(*cfg.yaw_deg))
    if cfg.frontal_rate > 0 and rng.uniform() < cfg.frontal_rate:  # no draw at 0: the old streams
        yaw = math.radians(facing_deg + rng.uniform(*cfg.frontal_yaw_deg))
    elev = math.radians(rng.uniform(*cfg.elevation_deg))
    roll = math.radians(rng.normal(0.0, cfg.roll_sd_deg) + roll_deg)
    view = "normal"
    if rng.uniform() < cfg.rare_rate:
        view = ("above", "below", "upside_down")[int(rng.integers(3))]
        if view == "above":
            elev = math.radians(rng.uniform(55.0, 85.0))
        elif view == "below":
            elev = math.radians(rng.uniform(-50.0, -25.0))
        else:
            roll += math.pi
    fill = float(rng.uniform(*cfg.fill))
    truncated = bool(rng.uniform() < cfg.truncation_rate)
    out_frac, side = 0.0, 0
    height = None
    if cfg.height_m and view in ("normal", "upside_down"):
        height = float(rng.uniform(*cfg.height_m))

    def eye(dist: float) -> np.ndarray:
        """The camera centre at ``dist`` from the people's centre (at ``height`` when given)."""
        e = elev if height is None else math.asin(float(np.clip((height - centre[1]) / dist, -0.99, 0.99)))
        return centre + dist * np.array([math.sin(yaw) * math.cos(e), math.sin(e), math.cos(yaw) * math.cos(e)])

    # Distance: the projected box height scales like 1 / distance; two corrections suffice.
    radius = float(np.linalg.norm(pts - centre, axis=1).max())
    dist = max(2.0 * radius, f_px * 2.0 * radius / (fill * cfg.height))
    for _ in range(3):
        cam = aimed_camera(eye(dist), centre, roll, f_px, cfg)
        if (cam.world_to_camera(pts)[:, 2] <= 0.05).any():
            dist *= 1.5
            continue
        b = _box(cam, pts)
        size = max(b[3] - b[1], (b[2] - b[0]) * cfg.height / cfg.width)
        dist *= size / (fill * cfg.height)
        dist = max(dist, 1.05 * radius + 0.1)
    cam = aimed_camera(eye(dist), centre, roll, f_px, cfg)
    b = _box(cam, pts)
    if not truncated:
        # Whole person in frame: back off until the box fits inside the image with a margin.
        for _ in range(20):
            if b[0] >= 1 and b[1] >= 1 and b[2] <= cfg.width - 1 and b[3] <= cfg.height - 1:
                break
            dist *= 1.1
            cam = aimed_camera(eye(dist), centre, roll, f_px, cfg)
            b = _box(cam, pts)
        else:  # pragma: no cover - needs a field of view smaller than the person
            raise ValueError("cannot fit the person in frame; widen focal_mm or lower fill")
    else:
        # Move the image window (the principal point) so that a fraction out_frac of the person's
        # box leaves the frame across one side: centre the box, then shift it by
        # (image - box) / 2 + out_frac * box along that side's axis.
        out_frac = float(rng.uniform(0.15, 0.5))
        side = int(rng.integers(4))  # 0 left, 1 right, 2 top, 3 bottom
        k = cam.K.copy()
        k[0, 2] += cfg.width / 2 - 0.5 * (b[0] + b[2])
        k[1, 2] += cfg.height / 2 - 0.5 * (b[1] + b[3])
        axis, size, dim = (0, b[2] - b[0], cfg.width) if side < 2 else (1, b[3] - b[1], cfg.height)
        shift = max(0.0, (dim - size) / 2) + out_frac * size
        k[axis, 2] += shift if side in (1, 3) else -shift
        cam = Camera(K=k, R=cam.R, t=cam.t, width=cfg.width, height=cfg.height)
    info = {
        "view": view,
        "focal_mm": f_mm,
        "yaw_deg": math.degrees(yaw),
        "elevation_deg": math.degrees(elev),
        "roll_deg": math.degrees(roll),
        "distance": float(dist),
        "fill": fill,
        "truncated": truncated,
        "truncation": out_frac if truncated else 0.0,
        "truncation_side": ("left", "right", "top", "bottom")[side] if truncated else "",
    }
    if cfg.f_number:
        info["f_number"] = float(math.exp(rng.uniform(math.log(cfg.f_number[0]), math.log(cfg.f_number[1]))))
        info["focus_m"] = float(cam.world_to_camera(centre[None])[0, 2])
    if height is not None:
        centre_y = float(eye(dist)[1])
        info["elevation_deg"] = math.degrees(math.asin(float(np.clip((centre_y - centre[1]) / dist, -1.0, 1.0))))
        info["height_m"] = centre_y
    return cam, info
