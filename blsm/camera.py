"""OpenCV pinhole cameras: the :class:`Camera` record and helpers that aim and frame one.

Conventions: metres, world Y up, bodies face +Z at rest.  Camera axes follow OpenCV: x right,
y down, z forward.  ``K`` is the (3, 3) intrinsic matrix in pixels and ``R, t`` map world to
camera (``X_cam = R @ X_world + t``).  A pixel with integer index ``(col, row)`` covers
``[col, col + 1] x [row, row + 1]``, so pixel centres sit at integer + 0.5 and a centred camera
has its principal point at ``(W / 2, H / 2)``.

Pure numpy: renderers (:mod:`blsm.render`, :mod:`synth.render`) turn a :class:`Camera` into their
own sensor (see :mod:`blsm.mitsuba_util`), the label and data code projects with it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["Camera", "Mesh", "auto_camera", "look_at_camera"]

Mesh = tuple[np.ndarray, np.ndarray]
"""A triangle mesh: vertices (V, 3) in metres and integer faces (F, 3)."""


@dataclass(frozen=True, eq=False)
class Camera:
    """OpenCV pinhole camera (x right, y down, z forward), immutable.

    A world point ``X`` (metres) maps to camera coordinates ``R @ X + t`` and to pixels
    ``(u, v) = (x / z, y / z)`` of ``K @ (R @ X + t)``; u grows to the right, v downwards, and
    the centre of pixel ``(col, row)`` is ``(col + 0.5, row + 0.5)``.

    Attributes:
        K: (3, 3) float64 intrinsics in pixels (focal lengths, principal point).
        R: (3, 3) float64 world-to-camera rotation (proper: orthonormal, det +1).
        t: (3,) float64 world-to-camera translation, metres.
        width: Image width in pixels.
        height: Image height in pixels.

    Raises:
        ValueError: On wrong shapes, non-finite values, an improper ``R`` or a non-positive size.
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        K = np.array(self.K, dtype=np.float64)
        R = np.array(self.R, dtype=np.float64)
        t = np.array(self.t, dtype=np.float64).reshape(-1)
        if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,):
            raise ValueError(
                f"Camera expects K (3, 3), R (3, 3), t (3,); got {K.shape}, {R.shape}, {t.shape}."
            )
        if not (np.isfinite(K).all() and np.isfinite(R).all() and np.isfinite(t).all()):
            raise ValueError("Camera K, R and t must be finite.")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
            raise ValueError("Camera R must be a proper rotation matrix (orthonormal, det +1).")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"Camera size must be positive, got {self.width}x{self.height}.")
        for name, arr in (("K", K), ("R", R), ("t", t)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, (3,) metres (``-R^T t``)."""
        return -self.R.T @ self.t

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """Transforms world points into camera coordinates.

        Args:
            points: (N, 3) world points, metres.

        Returns:
            (N, 3) points in the OpenCV camera frame (x right, y down, z forward), metres.

        Raises:
            ValueError: If ``points`` is not (N, 3).
        """
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {pts.shape}.")
        return pts @ self.R.T + self.t

    def project(self, points: np.ndarray) -> np.ndarray:
        """Projects world points to pixel coordinates.

        Points behind the camera (z <= 0) give meaningless coordinates; check
        ``world_to_camera(points)[:, 2] > 0`` if that matters.

        Args:
            points: (N, 3) world points, metres.

        Returns:
            (N, 2) pixel coordinates (u right, v down; pixel centres at integer + 0.5).
        """
        cam = self.world_to_camera(points)
        uvw = cam @ self.K.T
        return uvw[:, :2] / uvw[:, 2:3]


def look_at_camera(
    eye: Sequence[float] | np.ndarray,
    target: Sequence[float] | np.ndarray,
    up: Sequence[float] | np.ndarray = (0.0, 1.0, 0.0),
    fov_y_deg: float = 30.0,
    width: int = 192,
    height: int = 256,
) -> Camera:
    """Builds a centred OpenCV camera at ``eye`` looking at ``target``.

    The camera's z axis points from ``eye`` to ``target``, its y axis (image down) is the
    component of ``-up`` orthogonal to z, and the focal length is set from ``fov_y_deg``.

    Args:
        eye: (3,) camera centre in world coordinates, metres.
        target: (3,) world point (metres) that projects to the image centre ``(W / 2, H / 2)``.
        up: (3,) world direction that appears up in the image.
        fov_y_deg: Vertical field of view in degrees, in (0, 180).
        width: Image width in pixels.
        height: Image height in pixels.

    Returns:
        Camera with square pixels, no skew and principal point (W / 2, H / 2).

    Raises:
        ValueError: On a degenerate configuration.
    """
    eye_a = np.asarray(eye, dtype=np.float64).reshape(-1)
    target_a = np.asarray(target, dtype=np.float64).reshape(-1)
    up_a = np.asarray(up, dtype=np.float64).reshape(-1)
    if eye_a.shape != (3,) or target_a.shape != (3,) or up_a.shape != (3,):
        raise ValueError("eye, target and up must each be 3-vectors.")
    if not 0.0 < fov_y_deg < 180.0:
        raise ValueError(f"fov_y_deg must be in (0, 180), got {fov_y_deg}.")
    if width <= 0 or height <= 0:
        raise ValueError(f"width and height must be positive, got {width}x{height}.")
    forward = target_a - eye_a
    dist = np.linalg.norm(forward)
    if dist < 1e-12:
        raise ValueError("eye and target coincide; move the camera away from the target.")
    z = forward / dist
    x = np.cross(z, up_a)
    nx = np.linalg.norm(x)
    if nx < 1e-9:
        raise ValueError("up is parallel to the viewing direction; choose a different up vector.")
    x /= nx
    y = np.cross(z, x)  # points down in the image
    R = np.stack([x, y, z], axis=0)
    t = -R @ eye_a
    f = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2.0)
    K = np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])
    return Camera(K=K, R=R, t=t, width=width, height=height)


def auto_camera(
    meshes: Sequence[Mesh],
    width: int = 192,
    height: int = 256,
    *,
    fov_y_deg: float = 30.0,
    elevation_deg: float = 10.0,
    azimuth_deg: float = 0.0,
    margin: float = 1.08,
) -> Camera:
    """Front-view camera that frames all meshes' bounding box.

    The camera looks at the bounding-box centre from +Z (the front of a body
    at rest), raised by ``elevation_deg`` and rotated about +Y by
    ``azimuth_deg``; the distance is the smallest one at which all eight box
    corners fit inside the image shrunk by ``margin``.

    Args:
        meshes: List of (vertices (V, 3) metres, faces (F, 3)).
        width: Image width in pixels.
        height: Image height in pixels.
        fov_y_deg: Vertical field of view in degrees.
        elevation_deg: Camera elevation above the horizontal, degrees.
        azimuth_deg: Rotation of the view direction about +Y, degrees.
        margin: >= 1; extra border around the box (1.08 = 8 %).

    Returns:
        Centred camera of size ``width x height``.

    Raises:
        ValueError: On no meshes, non-finite or empty vertices, or ``margin < 1``.
    """
    if not meshes:
        raise ValueError("auto_camera() needs at least one mesh to frame.")
    if margin < 1.0:
        raise ValueError(f"margin must be >= 1, got {margin}.")
    pts = np.concatenate([np.asarray(v, dtype=np.float64).reshape(-1, 3) for v, _ in meshes])
    if pts.size == 0 or not np.isfinite(pts).all():
        raise ValueError("auto_camera() needs finite, non-empty vertex arrays.")
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    center = 0.5 * (lo + hi)
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    direction = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    # Camera axes only depend on the direction; place at unit distance first.
    probe = look_at_camera(center + direction, center, fov_y_deg=fov_y_deg, width=width, height=height)
    rel = (corners - center) @ probe.R.T  # corner offsets in camera axes
    tan_y = (height / 2.0) / probe.K[1, 1]
    tan_x = (width / 2.0) / probe.K[0, 0]
    need_x = np.abs(rel[:, 0]) * margin / tan_x - rel[:, 2]
    need_y = np.abs(rel[:, 1]) * margin / tan_y - rel[:, 2]
    extent = float(np.linalg.norm(hi - lo))
    dist = max(
        float(need_x.max()),
        float(need_y.max()),
        1e-3 + float(-rel[:, 2].min()),  # keep every corner in front of the camera
        1e-3 * max(extent, 1.0),
    )
    return look_at_camera(center + dist * direction, center, fov_y_deg=fov_y_deg, width=width, height=height)
