"""Multi-view renders of a scan: cameras on a sphere around it (thesis Sec. 6.3.1).

"We render each scan from multiple views where the cameras are sampled uniformly from a sphere."
:func:`view_cameras` puts C OpenCV cameras (:class:`blsm.camera.Camera`: x right, y down, z
forward; ``K``, ``R``, ``t`` world to camera; pixel centres at integer + 0.5) on a Fibonacci lattice
of the spherical zone between ``min_elevation_deg`` and ``max_elevation_deg`` (uniform in area over
that zone; steep views from below the floor are left out, a scanner does not see through its floor),
all looking at the scan's centre from the distance at which its bounding sphere fills the image
with a margin. :func:`render_views` renders the scan with its vertex colours (a uniform clay grey
if it has none) through :func:`blsm.render.render_meshes`: one Mitsuba scene per scan topology,
only the camera (and the camera-relative key and fill lights) change per view. The Mitsuba variant
is chosen once by :func:`blsm.mitsuba_util.resolve_variant` (``llvm_ad_rgb``, else ``scalar_rgb``).

The scan's frame (centre, radius) and the per-view person boxes use vertex quantiles
(``frame_quantile``, 0.2 % by default at each end of each axis) rather than the extremes, so a few
stray vertices far away (a marker on the floor, scanner debris) do not shrink the body in the image.
The scan is the only thing rendered (no floor, no background objects beyond what the scan holds),
so the projected box of the scan is the person's box unless the scan holds other objects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from blsm.camera import Camera, look_at_camera

CLAY = (0.72, 0.66, 0.60)
"""sRGB colour of a scan without vertex colours."""


@dataclass(frozen=True)
class ViewConfig:
    """The virtual cameras and renders.

    Attributes:
        views: C, the number of cameras (18).
        resolution: square image side, pixels (448).
        fov_deg: field of view across the image, degrees (40: focal length 615 px at 448 px).
        min_elevation_deg, max_elevation_deg: the camera zone's elevation range above the
            horizontal through the scan's centre, degrees (-15 to 55).
        margin: the bounding sphere's radius times this fills half the image (1.1).
        spp: samples per pixel (4).
        frame_quantile: vertex quantile at each end of each axis for the frame and the boxes.
        background: sRGB background colour.
        variant: Mitsuba variant, None = choose (``llvm_ad_rgb``, else ``scalar_rgb``).
    """

    views: int = 18
    resolution: int = 448
    fov_deg: float = 40.0
    min_elevation_deg: float = -15.0
    max_elevation_deg: float = 55.0
    margin: float = 1.1
    spp: int = 4
    frame_quantile: float = 0.002
    background: tuple[float, float, float] = (0.55, 0.57, 0.6)
    variant: str | None = None

    def __post_init__(self) -> None:
        if self.views < 2 or self.resolution < 16:
            raise ValueError(f"ViewConfig needs views >= 2 and resolution >= 16, got {self.views}, {self.resolution}")
        if not -90.0 <= self.min_elevation_deg < self.max_elevation_deg <= 90.0:
            raise ValueError("ViewConfig needs -90 <= min_elevation_deg < max_elevation_deg <= 90")
        if not 0.0 < self.fov_deg < 150.0 or self.margin < 1.0 or not 0.0 <= self.frame_quantile < 0.5:
            raise ValueError("ViewConfig needs 0 < fov_deg < 150, margin >= 1, 0 <= frame_quantile < 0.5")


def sphere_directions(n: int, min_elevation_deg: float, max_elevation_deg: float) -> np.ndarray:
    """(n, 3) unit directions, a Fibonacci lattice over the zone of the unit sphere between two
    elevations (Y up): heights uniform in sin(elevation), azimuths by the golden angle."""
    lo, hi = (math.sin(math.radians(e)) for e in (min_elevation_deg, max_elevation_deg))
    i = np.arange(n) + 0.5
    y = lo + (hi - lo) * i / n
    az = i * math.pi * (3.0 - math.sqrt(5.0))
    r = np.sqrt(1.0 - y**2)
    return np.stack([r * np.sin(az), y, r * np.cos(az)], axis=1)


def scan_frame(vertices: np.ndarray, quantile: float = 0.002) -> tuple[np.ndarray, float]:
    """(centre (3,), radius): the centre and half-diagonal of the scan's quantile box, metres."""
    lo, hi = np.quantile(vertices, [quantile, 1.0 - quantile], axis=0)
    return 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))


def view_cameras(vertices: np.ndarray, cfg: ViewConfig = ViewConfig()) -> list[Camera]:
    """C cameras on a sphere around the scan, looking at its centre (see the module docstring).

    Args:
        vertices: (N, 3) the scan's vertices, metres.
        cfg: the views.

    Returns:
        C :class:`Camera` (square images of ``cfg.resolution`` pixels, principal point at the centre).
    """
    centre, radius = scan_frame(np.asarray(vertices, np.float64), cfg.frame_quantile)
    dist = radius * cfg.margin / math.sin(math.radians(cfg.fov_deg) / 2.0)
    dirs = sphere_directions(cfg.views, cfg.min_elevation_deg, cfg.max_elevation_deg)
    n = cfg.resolution
    # look_at_camera's field of view is vertical; the image is square, so it is the horizontal one too.
    return [look_at_camera(centre + dist * d, centre, fov_y_deg=cfg.fov_deg, width=n, height=n) for d in dirs]


def view_boxes(vertices: np.ndarray, cameras: list[Camera], quantile: float = 0.002) -> np.ndarray:
    """(C, 4) per view the box ``(x0, y0, x1, y1)`` of the projected scan, pixels (quantiles of the
    projected vertices, clipped to the image)."""
    out = np.zeros((len(cameras), 4))
    for i, cam in enumerate(cameras):
        uv = cam.project(np.asarray(vertices, np.float64))
        lo, hi = np.quantile(uv, [quantile, 1.0 - quantile], axis=0)
        out[i] = np.clip([lo[0], lo[1], hi[0], hi[1]], 0.0, [cam.width, cam.height, cam.width, cam.height])
    return out


def render_views(
    vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None, cameras: list[Camera], cfg: ViewConfig
) -> list[np.ndarray]:
    """Render the scan from each camera.

    Args:
        vertices: (N, 3) metres; faces: (F, 3); colors: (N, 3) uint8 or float sRGB, or None (clay).
        cameras: the views (:func:`view_cameras`).
        cfg: spp, background and variant.

    Returns:
        C images, each (H, W, 3) uint8 sRGB.
    """
    from blsm import render
    from blsm.mitsuba_util import resolve_variant

    variant = resolve_variant(cfg.variant)
    mesh = (np.asarray(vertices, np.float32), np.asarray(faces, np.int64))
    vc = None if colors is None else [np.asarray(colors)]
    images = []
    for cam in cameras:
        img = render.render_meshes(
            [mesh], cam, colors=[CLAY], vertex_colors=vc, spp=cfg.spp, background=cfg.background, variant=variant
        )
        images.append((np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8))
    return images


def render_scan(
    vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None, cfg: ViewConfig = ViewConfig()
) -> tuple[list[Camera], np.ndarray, list[np.ndarray]]:
    """The registration's views of a scan: (:func:`view_cameras`, :func:`view_boxes`, :func:`render_views`)."""
    cameras = view_cameras(vertices, cfg)
    boxes = view_boxes(vertices, cameras, cfg.frame_quantile)
    return cameras, boxes, render_views(vertices, faces, colors, cameras, cfg)
