"""Camera paths of a sequence: exact OpenCV cameras ``K``, ``R``, ``t`` at any time of a clip.

A sequence draws one path kind by the weights of ``sequence.cameras`` (:class:`synth.config.CameraPaths`)
and the path's parameters, uniformly in their ``[low, high]`` ranges. Every path starts from a base
camera drawn by :func:`synth.camera.sample_camera` (focal length, height, yaw, distance by ``fill``;
no rare view, no truncation) that frames **all the people over the whole clip**, except ``pan`` and
``tracking``, which frame the followed person (``follow``, person 0) at the first frame. ``D`` is the
clip's duration, ``t`` the time in seconds from its start:

=============  ===================================================================================
``static``     the base camera throughout (a tripod)
``pan``        the camera stays at the base position and turns to aim at the followed person's
               centre, smoothed over ``pan_smoothing_s`` (a Gaussian's standard deviation, seconds):
               pan and tilt, no roll change
``dolly``      the camera slides by ``dolly_m`` metres (either sign) along one of its own axes, x
               (truck), y (pedestal) or z (push in / pull out), linearly over the clip; it does not
               turn. A push towards the people is limited to half the base distance and a pedestal
               stays 0.2 m above the ground
``orbit``      the camera circles the vertical axis through the people's centre at ``orbit_deg_s``
               degrees a second (either sense), aimed at the centre, at the base height
``tracking``   the camera keeps its base offset from the followed person's centre, smoothed over
               ``tracking_smoothing_s`` seconds, horizontally (a dolly track or a gimbal at a fixed
               height); it does not turn
``zoom``       a tripod camera aimed at the followed person's mean centre over the clip, whose focal
               length changes log-linearly by ``zoom_ratio`` over the clip: zooming in from the
               base focal length, or out towards it
``handheld``   the base camera with shake: per axis (pan, tilt, roll) a low-frequency sinusoid of
               amplitude ``shake_low_deg`` at ``shake_low_hz`` plus a high-frequency one of
               ``shake_high_deg`` at ``shake_high_hz``, random phases; and the centre moving by
               ``shake_m`` metres per axis at a low frequency
``portrait``   a static camera rolled by 90 degrees (either way): a phone held upright, its video
               stored sideways
``long_lens``  a static tripod far away with a focal length in ``long_lens_mm`` (full-frame mm)
=============  ===================================================================================

:meth:`CameraPath.at` evaluates any time, so a motion-blurred frame's sub-frames see the camera
where it is at their own times.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from blsm.camera import Camera
from synth.camera import SENSOR_WIDTH_MM, CameraConfig, aimed_camera, sample_camera

PATHS = ("static", "pan", "dolly", "orbit", "tracking", "zoom", "handheld", "portrait", "long_lens")
FOLLOWING = ("pan", "tracking")


@dataclass(frozen=True)
class Track:
    """A smoothed centre over time: ``times`` (N,) seconds ascending, ``points`` (N, 3)."""

    times: np.ndarray
    points: np.ndarray

    def smoothed(self, sigma_s: float) -> Track:
        """The centre filtered by a Gaussian of ``sigma_s`` seconds (a straight line stays itself)."""
        if sigma_s <= 0 or len(self.times) < 2:
            return self
        from scipy.ndimage import gaussian_filter1d

        dt = float(np.median(np.diff(self.times)))
        # The ends are extended by point reflection, so that a steady walk is followed without lag.
        pad = int(math.ceil(4 * sigma_s / dt)) + 1
        ext = np.pad(self.points, ((pad, pad), (0, 0)), mode="reflect", reflect_type="odd")
        return Track(self.times, gaussian_filter1d(ext, sigma_s / dt, axis=0, mode="nearest")[pad:-pad])

    def at(self, t: float) -> np.ndarray:
        return np.array([np.interp(t, self.times, self.points[:, k]) for k in range(3)])


@dataclass
class CameraPath:
    """One sequence's camera: ``at(t)`` is the exact camera at time ``t`` seconds; ``info`` the
    path's kind and drawn parameters (recorded as ``camera.path`` in every frame's labels) and
    ``base`` what :func:`synth.camera.sample_camera` drew for the base camera."""

    kind: str
    cfg: CameraConfig
    eye: np.ndarray
    target: np.ndarray
    roll: float
    focal_px: float
    R: np.ndarray
    duration: float
    params: dict[str, Any] = field(default_factory=dict)
    base: dict[str, Any] = field(default_factory=dict)
    follow: Track | None = None

    @property
    def info(self) -> dict[str, Any]:
        return {"kind": self.kind, **self.params}

    def at(self, t: float) -> Camera:
        k, p, w, h = self.kind, self.params, self.cfg.width, self.cfg.height
        u = t / self.duration if self.duration > 0 else 0.0
        if k == "pan":
            assert self.follow is not None
            return aimed_camera(self.eye, self.follow.at(t), self.roll, self.focal_px, self.cfg)
        if k == "orbit":
            a = math.radians(p["deg_s"]) * t
            c, s = math.cos(a), math.sin(a)
            rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
            return aimed_camera(
                self.target + rot @ (self.eye - self.target), self.target, self.roll, self.focal_px, self.cfg
            )
        if k == "zoom":
            e = u if p["direction"] == "in" else 1.0 - u
            return aimed_camera(self.eye, self.target, self.roll, self.focal_px * p["ratio"] ** e, self.cfg)
        eye, r = self.eye, self.R
        if k == "dolly":
            eye = eye + u * p["distance_m"] * np.asarray(p["direction"])
        elif k == "tracking":
            assert self.follow is not None
            d = self.follow.at(t) - self.follow.at(0.0)
            eye = eye + np.array([d[0], 0.0, d[2]])
        elif k == "handheld":
            from scipy.spatial.transform import Rotation

            ang = [
                sum(a * math.sin(2 * math.pi * f * t + ph) for a, f, ph in p["rotation"][i]) for i in range(3)
            ]
            shake = Rotation.from_euler("yxz", np.radians([ang[0], ang[1], ang[2]])).as_matrix()
            r = shake @ r
            eye = eye + np.array([a * math.sin(2 * math.pi * f * t + ph) for a, f, ph in p["translation"]])
        kk = np.array([[self.focal_px, 0.0, w / 2.0], [0.0, self.focal_px, h / 2.0], [0.0, 0.0, 1.0]])
        return Camera(K=kk, R=r, t=-r @ eye, width=w, height=h)


def choose_kind(weights: dict[str, float], rng: np.random.Generator) -> str:
    names = [k for k in PATHS if weights.get(k, 0.0) > 0]
    w = np.array([weights[k] for k in names], np.float64)
    return names[int(rng.choice(len(names), p=w / w.sum()))]


def _u(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    return float(rng.uniform(lo_hi[0], lo_hi[1]))


def sample_path(
    kind: str,
    cam_cfg: CameraConfig,
    paths: Any,
    everyone: np.ndarray,
    followed: np.ndarray,
    follow: Track,
    duration: float,
    rng: np.random.Generator,
) -> CameraPath:
    """Draw a camera path of ``kind`` (:data:`PATHS`).

    Args:
        cam_cfg: the dataset's camera ranges (image size, focal length, height, fill, roll).
        paths: :class:`synth.config.CameraPaths`.
        everyone: (N, 3) points of all people over the whole clip (hull vertices), world metres.
        followed: (M, 3) the followed person's points at the first frame.
        follow: the followed person's centre over the clip (unsmoothed).
        duration: the clip's duration, seconds.
    """
    if kind not in PATHS:
        raise ValueError(f"unknown camera path {kind!r} (known: {', '.join(PATHS)})")
    cfg = dataclasses.replace(cam_cfg, rare_rate=0.0, truncation_rate=0.0)
    if kind == "long_lens":
        cfg = dataclasses.replace(cfg, focal_mm=tuple(paths.long_lens_mm), f_number=())
    roll_deg = float(rng.choice([-90.0, 90.0])) if kind == "portrait" else 0.0
    pts = followed if kind in FOLLOWING else everyone
    cam, base = sample_camera(pts, cfg, rng, roll_deg=roll_deg)
    eye = -cam.R.T @ cam.t
    target = 0.5 * (pts.min(0) + pts.max(0))
    path = CameraPath(
        kind,
        cfg,
        eye,
        target,
        math.radians(base["roll_deg"]),
        float(cam.K[0, 0]),
        cam.R.copy(),
        duration,
        base={
            k: v
            for k, v in base.items()
            if k in ("focal_mm", "yaw_deg", "elevation_deg", "roll_deg", "distance", "fill", "height_m")
        },
    )
    p: dict[str, Any] = {}
    if kind in FOLLOWING:
        sigma = paths.pan_smoothing_s if kind == "pan" else paths.tracking_smoothing_s
        path.follow = follow.smoothed(sigma)
        p.update(follow=0, smoothing_s=sigma)
    elif kind == "dolly":
        axis = int(rng.integers(3))
        dist = _u(rng, paths.dolly_m) * float(rng.choice([-1.0, 1.0]))
        direction = cam.R.T[:, axis].copy()  # the camera's own x, y (down) or z (forward) in the world
        if axis == 2 and dist > 0:
            dist = min(dist, 0.5 * float(np.linalg.norm(target - eye)))
        end_y = eye[1] + dist * direction[1]
        if end_y < 0.2:
            dist = (0.2 - eye[1]) / direction[1] if abs(direction[1]) > 1e-6 else 0.0
        p.update(axis="xyz"[axis], distance_m=dist, direction=direction.tolist())
    elif kind == "orbit":
        p.update(deg_s=_u(rng, paths.orbit_deg_s) * float(rng.choice([-1.0, 1.0])), centre=target.tolist())
    elif kind == "zoom":  # towards the followed person's mean centre over the clip
        path.target = follow.points.mean(0)
        p.update(ratio=_u(rng, paths.zoom_ratio), direction=str(rng.choice(["in", "out"])))
    elif kind == "handheld":
        p["rotation"] = [
            [(_u(rng, paths.shake_low_deg), _u(rng, paths.shake_low_hz), _u(rng, (0, 2 * math.pi))),
             (_u(rng, paths.shake_high_deg), _u(rng, paths.shake_high_hz), _u(rng, (0, 2 * math.pi)))]
            for _ in range(3)
        ]  # fmt: skip
        p["translation"] = [(_u(rng, paths.shake_m), _u(rng, paths.shake_low_hz), _u(rng, (0, 2 * math.pi)))
                            for _ in range(3)]  # fmt: skip
        p["axes"] = (
            "pan (about the camera's up), tilt, roll; [amplitude deg, Hz, phase rad]; translation [m, Hz, phase]"
        )
    elif kind == "portrait":
        p["roll_deg"] = roll_deg
    elif kind == "long_lens":
        p["focal_mm"] = base["focal_mm"]
    path.params = p
    return path


def focal_mm(camera: Camera) -> float:
    """The full-frame-equivalent focal length (mm) of ``camera``."""
    return float(camera.K[0, 0]) * SENSOR_WIDTH_MM / camera.width
