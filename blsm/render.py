"""Clay-style rendering of triangle meshes with Mitsuba 3.

Conventions: metres, Y up, bodies face +Z at rest.  Cameras follow the OpenCV
pinhole model: camera axes x right, y down, z forward; ``K`` is 3x3 and
``R, t`` map world to camera (``X_cam = R @ X_world + t``).  A pixel with
integer index ``(col, row)`` covers ``[col, col + 1] x [row, row + 1]``, so
pixel centres sit at integer + 0.5 and a centred camera has its principal
point at ``(W / 2, H / 2)``.

Mitsuba is imported lazily: importing this module never imports mitsuba nor
sets a variant.  The variant is chosen by :func:`choose_variant`, which probes
candidates in a subprocess, because ``llvm_ad_rgb`` aborts the whole process
("LLVM ERROR: Cannot select ... fminimum") on machines with libLLVM 15.

Rendered images are returned as sRGB-encoded float32 in ``[0, 1]`` (ready to
save).  All colour inputs (``colors``, ``vertex_colors``, ``background``) are
likewise sRGB-encoded values in ``[0, 1]``; they are linearised internally.

The film is ``rgba`` (rather than ``rgb``) with emitters hidden, so the
alpha channel gives antialiased coverage and the background colour is
composited exactly in linear space.  Lighting uses the ``direct`` integrator
with camera-relative directional key/fill lights plus a weak constant
environment, and a low-discrepancy sampler to keep noise low at 16 spp.

Scenes are cached per (variant, mesh topology, film size, vertex-colour
layout).  Rendering a new frame with the same topology only updates vertex
positions, colours, the sensor and the camera-relative lights through
``mi.traverse(scene)`` + ``params.update()`` instead of reloading the scene.
"""

from __future__ import annotations

import hashlib
import math
import os
import subprocess
import sys
import warnings
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "Camera",
    "auto_camera",
    "choose_variant",
    "look_at_camera",
    "render_grid",
    "render_meshes",
    "save_png",
]

Mesh = tuple[np.ndarray, np.ndarray]
RGB = tuple[float, float, float]

VARIANT_ENV = "BLSM_MITSUBA_VARIANT"
"""Environment variable that forces a Mitsuba variant (still probed)."""

DEFAULT_PALETTE: tuple[RGB, ...] = (
    (0.78, 0.70, 0.62),  # clay
    (0.55, 0.68, 0.85),  # blue
    (0.62, 0.80, 0.58),  # green
    (0.88, 0.62, 0.55),  # red
    (0.80, 0.74, 0.50),  # yellow
    (0.72, 0.62, 0.82),  # purple
)
"""Default sRGB albedo per mesh index within a scene."""

_PROBE_TIMEOUT_S = 180.0
_SCENE_CACHE_SIZE = 8

# Module-level caches (filled lazily).
_CHOSEN_VARIANT: dict[tuple[str, ...], str] = {}
_PROBE_RESULTS: dict[str, tuple[bool, str]] = {}
_SCENE_CACHE: OrderedDict[tuple[Any, ...], _SceneRenderer] = OrderedDict()

_PROBE_SCRIPT = r"""
import sys
import mitsuba as mi
mi.set_variant(sys.argv[1])
mesh = mi.Mesh("probe", 3, 1, has_vertex_normals=True)
params = mi.traverse(mesh)
# Buffer types differ between JIT (mi.Float) and scalar (ArrayXf) variants.
params["vertex_positions"] = type(params["vertex_positions"])(
    [-0.5, -0.5, 0.0, 0.5, -0.5, 0.0, 0.0, 0.5, 0.0])
params["faces"] = type(params["faces"])([0, 1, 2])
params.update()
scene = mi.load_dict({
    "type": "scene",
    "integrator": {"type": "path", "max_depth": 3, "hide_emitters": True},
    "sensor": {
        "type": "perspective",
        "fov": 45.0,
        "to_world": mi.ScalarTransform4f().look_at(
            origin=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": 8, "height": 8,
                 "pixel_format": "rgba", "rfilter": {"type": "box"}},
    },
    "tri": mesh,
    "env": {"type": "constant", "radiance": {"type": "rgb", "value": [0.3, 0.3, 0.3]}},
    "key": {"type": "directional", "direction": [0.0, -0.5, -1.0],
            "irradiance": {"type": "rgb", "value": [2.0, 2.0, 2.0]}},
})
image = mi.TensorXf(mi.render(scene, spp=2)).numpy()
assert image.shape == (8, 8, 4), image.shape
assert (image == image).all(), "NaN in probe render"
assert image[..., 3].max() > 0.5, "probe triangle not visible"
print("BLSM_PROBE_OK")
"""


# --------------------------------------------------------------------------
# Variant selection
# --------------------------------------------------------------------------


def _probe_variant(variant: str, timeout: float = _PROBE_TIMEOUT_S) -> tuple[bool, str]:
    """Checks in a subprocess that ``variant`` can load and render a scene.

    Args:
        variant: Mitsuba variant name, e.g. ``"llvm_ad_rgb"``.
        timeout: Seconds before the probe is considered failed.

    Returns:
        ``(ok, reason)``; ``reason`` is empty on success, otherwise the most
        informative line of the subprocess's stderr.
    """
    if variant in _PROBE_RESULTS:
        return _PROBE_RESULTS[variant]
    try:
        proc = subprocess.run(
            [sys.executable, "-c", _PROBE_SCRIPT, variant],
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
        )
    except subprocess.TimeoutExpired:
        result = (False, f"probe timed out after {timeout:.0f} s")
    except OSError as exc:  # e.g. sys.executable missing
        result = (False, f"could not start probe subprocess: {exc}")
    else:
        if proc.returncode == 0 and "BLSM_PROBE_OK" in proc.stdout:
            result = (True, "")
        else:
            lines = [ln.strip() for ln in proc.stderr.splitlines() if ln.strip()]
            llvm = [ln for ln in lines if "LLVM ERROR" in ln]
            if llvm:
                reason = llvm[-1]
            elif lines:
                reason = lines[-1]
            else:
                reason = f"probe exited with code {proc.returncode} and no stderr"
            if proc.returncode < 0:
                reason += f" (killed by signal {-proc.returncode})"
            result = (False, reason)
    _PROBE_RESULTS[variant] = result
    return result


def choose_variant(preferred: tuple[str, ...] = ("llvm_ad_rgb", "scalar_rgb")) -> str:
    """Returns the first Mitsuba variant from ``preferred`` that actually works.

    Each candidate is probed in a subprocess (load + render a tiny triangle
    scene) so that a hard abort inside LLVM cannot kill the caller.  The result
    is cached per candidate tuple for the lifetime of the process.  The
    environment variable ``BLSM_MITSUBA_VARIANT`` forces a single variant,
    which is still probed.  This function does not call ``mi.set_variant``.

    Args:
        preferred: Candidate variants, best first.

    Returns:
        The name of a working variant.

    Raises:
        ValueError: If ``preferred`` is empty.
        RuntimeError: If no candidate can render.
    """
    forced = os.environ.get(VARIANT_ENV, "").strip()
    candidates = (forced,) if forced else tuple(preferred)
    if not candidates:
        raise ValueError(
            "choose_variant() needs at least one candidate variant, e.g. ('llvm_ad_rgb', 'scalar_rgb')."
        )
    if candidates in _CHOSEN_VARIANT:
        return _CHOSEN_VARIANT[candidates]

    failures: list[tuple[str, str]] = []
    for variant in candidates:
        ok, reason = _probe_variant(variant)
        if ok:
            if failures:
                failed_desc = "; ".join(f"{v!r}: {r}" for v, r in failures)
                warnings.warn(
                    f"Mitsuba variant(s) unusable on this machine ({failed_desc}); "
                    f"falling back to {variant!r}, which is much slower. If the failure is "
                    "'LLVM ERROR: Cannot select ...' the system libLLVM is too old: "
                    "`apt-get install -y libllvm19` fixes it.",
                    RuntimeWarning,
                    stacklevel=2,
                )
            _CHOSEN_VARIANT[candidates] = variant
            return variant
        failures.append((variant, reason))

    failed_desc = "; ".join(f"{v!r}: {r}" for v, r in failures)
    hint = f" (forced by ${VARIANT_ENV}; unset it or pick another variant)" if forced else ""
    raise RuntimeError(
        f"No Mitsuba variant could render{hint}: {failed_desc}. "
        "Check that mitsuba is installed in this interpreter; for LLVM variants "
        "`apt-get install -y libllvm19` provides a compatible libLLVM."
    )


def _resolve_variant(variant: str | None) -> str:
    """Returns a validated variant (``choose_variant()`` when ``None``)."""
    if variant is None:
        return choose_variant()
    ok, reason = _probe_variant(variant)
    if not ok:
        raise RuntimeError(
            f"Mitsuba variant {variant!r} cannot render on this machine: {reason}. "
            "Pass variant=None to pick a working one automatically."
        )
    return variant


def _mitsuba(variant: str) -> Any:
    """Imports mitsuba and activates ``variant`` (only if not already active)."""
    import mitsuba as mi

    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi


# --------------------------------------------------------------------------
# Cameras
# --------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Camera:
    """OpenCV pinhole camera (x right, y down, z forward).

    Attributes:
        K: (3, 3) float64 intrinsics; pixel centres at integer + 0.5.
        R: (3, 3) float64 world-to-camera rotation.
        t: (3,) float64 world-to-camera translation.
        width: Image width in pixels.
        height: Image height in pixels.
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
        """Camera centre in world coordinates, (3,)."""
        return -self.R.T @ self.t

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """Transforms world points into camera coordinates.

        Args:
            points: (N, 3) world points.

        Returns:
            (N, 3) points in the OpenCV camera frame.
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
            points: (N, 3) world points.

        Returns:
            (N, 2) pixel coordinates (u right, v down; pixel centres at +0.5).
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

    Args:
        eye: (3,) camera centre in world coordinates.
        target: (3,) point that projects to the image centre.
        up: (3,) world direction that appears up in the image.
        fov_y_deg: Vertical field of view in degrees, in (0, 180).
        width: Image width in pixels.
        height: Image height in pixels.

    Returns:
        Camera with square pixels and principal point (W / 2, H / 2).

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
        meshes: List of (vertices (V, 3), faces (F, 3)).
        width: Image width in pixels.
        height: Image height in pixels.
        fov_y_deg: Vertical field of view in degrees.
        elevation_deg: Camera elevation above the horizontal, degrees.
        azimuth_deg: Rotation of the view direction about +Y, degrees.
        margin: >= 1; extra border around the box (1.08 = 8 %).

    Returns:
        Camera of size ``width x height``.
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


# --------------------------------------------------------------------------
# Colour helpers
# --------------------------------------------------------------------------


def _unit_float(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c)
    return np.clip(c if c.dtype.kind == "f" else c.astype(np.float64), 0.0, 1.0)


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB values to linear (IEC 61966-2-1), clipped to [0, 1]; float arrays keep their dtype."""
    c = _unit_float(c)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(c.dtype, copy=False)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    """Linear values to sRGB (IEC 61966-2-1), clipped to [0, 1]; float arrays keep their dtype."""
    c = _unit_float(c)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055).astype(c.dtype, copy=False)


def _as_rgb(value: Sequence[float], what: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise ValueError(f"{what} must be an (r, g, b) triple of floats in [0, 1], got {value!r}.")
    return arr


# --------------------------------------------------------------------------
# Scene construction and reuse
# --------------------------------------------------------------------------

# Camera-relative lights (OpenCV camera axes: x right, y down, z forward).
# Each entry: (direction *towards* the light in camera axes, linear irradiance).
_KEY_LIGHT = (np.array([-0.65, -0.65, -0.45]), 2.8)
_FILL_LIGHT = (np.array([0.55, -0.15, -0.85]), 0.6)
_ENV_RADIANCE = 0.15
_LIGHTS = {"key": _KEY_LIGHT, "fill": _FILL_LIGHT}


def _validate_mesh(i: int, mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    try:
        verts, faces = mesh
    except (TypeError, ValueError):
        raise ValueError(f"meshes[{i}] must be a (vertices, faces) tuple.") from None
    v = np.asarray(verts, dtype=np.float32)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] < 3:
        raise ValueError(f"meshes[{i}] vertices must have shape (V, 3) with V >= 3, got {v.shape}.")
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] < 1:
        raise ValueError(f"meshes[{i}] faces must have shape (F, 3) with F >= 1, got {f.shape}.")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"meshes[{i}] faces must be an integer array, got dtype {f.dtype}.")
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise ValueError(f"meshes[{i}] faces index outside [0, {v.shape[0]}): min {f.min()}, max {f.max()}.")
    if not np.isfinite(v).all():
        raise ValueError(f"meshes[{i}] vertices contain NaN/inf; fix the mesh before rendering.")
    return np.ascontiguousarray(v), np.ascontiguousarray(f, dtype=np.uint32)


def _validate_vertex_colors(i: int, vc: np.ndarray, n_verts: int) -> np.ndarray:
    arr = np.asarray(vc)
    if arr.ndim != 2 or arr.shape[0] != n_verts or arr.shape[1] not in (3, 4):
        raise ValueError(
            f"vertex_colors[{i}] must have shape ({n_verts}, 3) or ({n_verts}, 4), got {arr.shape}."
        )
    arr = arr[:, :3]
    arr = arr.astype(np.float64) / 255.0 if arr.dtype == np.uint8 else arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise ValueError(f"vertex_colors[{i}] contains NaN/inf.")
    return srgb_to_linear(arr).astype(np.float32)


def _to_world_matrix(camera: Camera) -> np.ndarray:
    """Mitsuba sensor to_world (4, 4) reproducing an OpenCV camera.

    Mitsuba's sensor looks along local +Z with +Y up and +X to the *left* of
    the image, i.e. its local axes are OpenCV's (-x, -y, +z).
    """
    c2w = np.eye(4)
    c2w[:3, :3] = camera.R.T
    c2w[:3, 3] = camera.center
    c2w[:3, 0] *= -1.0
    c2w[:3, 1] *= -1.0
    return c2w


def _sensor_params(camera: Camera) -> tuple[float, float, float]:
    """Returns (x_fov_deg, principal_point_offset_x, principal_point_offset_y)."""
    K = camera.K
    fx, fy = K[0, 0], K[1, 1]
    if fx <= 0 or fy <= 0:
        raise ValueError(f"Camera focal lengths must be positive, got fx={fx}, fy={fy}.")
    if abs(fx - fy) > 1e-6 * max(fx, fy) or abs(K[0, 1]) > 1e-9:
        raise ValueError(
            "render_meshes() supports square pixels without skew only (K[0,0] == K[1,1], K[0,1] == 0); "
            "rescale the image or the intrinsics first."
        )
    x_fov = math.degrees(2.0 * math.atan(0.5 * camera.width / fx))
    # Offsets are fractions of the film size measured from the film centre;
    # Mitsuba's sign is opposite to the OpenCV pixel axes (checked by tests).
    ppx = -(K[0, 2] - 0.5 * camera.width) / camera.width
    ppy = -(K[1, 2] - 0.5 * camera.height) / camera.height
    return float(x_fov), float(ppx), float(ppy)


def _directional_to_world(direction: np.ndarray) -> np.ndarray:
    """(4, 4) transform whose local +Z maps to ``direction`` (unit)."""
    z = direction / np.linalg.norm(direction)
    helper = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = x, y, z
    return m


def _assign(params: Any, key: str, values: np.ndarray) -> None:
    """Sets a flat buffer parameter using its own array type.

    JIT variants use ``mi.Float``/``mi.UInt32``; scalar variants use
    ``drjit.scalar.ArrayXf``/``ArrayXu``, so the type is taken from the
    current value.
    """
    params[key] = type(params[key])(values)


class _SceneRenderer:
    """A loaded Mitsuba scene for one mesh topology, updated in place per frame."""

    def __init__(
        self,
        mi: Any,
        meshes: list[tuple[np.ndarray, np.ndarray]],
        has_vc: tuple[bool, ...],
        width: int,
        height: int,
        smooth: bool,
    ) -> None:
        self.mi = mi
        self.width, self.height = width, height
        self.mesh_ids = [f"mesh_{i}" for i in range(len(meshes))]
        scene: dict[str, Any] = {
            "type": "scene",
            # Direct lighting only: delta lights are noise-free, the weak constant
            # environment adds soft ambient occlusion (the only noisy term).
            "integrator": {"type": "direct", "hide_emitters": True},
            "sensor": {
                "type": "perspective",
                "fov": 40.0,
                "fov_axis": "x",
                "near_clip": 0.01,
                "far_clip": 1000.0,
                # Low-discrepancy samples stratify light selection: ~4x less
                # noise than "independent" at the same spp and cost.
                "sampler": {"type": "ldsampler", "sample_count": 4},
                "film": {
                    "type": "hdrfilm",
                    "width": width,
                    "height": height,
                    # rgba (not rgb): the alpha channel gives antialiased
                    # coverage so the background can be composited exactly.
                    "pixel_format": "rgba",
                    "rfilter": {"type": "box"},
                },
            },
            "env": {"type": "constant", "radiance": {"type": "rgb", "value": [_ENV_RADIANCE] * 3}},
        }
        for name, (_, irradiance) in _LIGHTS.items():
            scene[name] = {
                "type": "directional",
                "direction": [0.0, 0.0, -1.0],
                "irradiance": {"type": "rgb", "value": [irradiance] * 3},
            }
        for mid, (verts, faces), vc in zip(self.mesh_ids, meshes, has_vc):
            props = mi.Properties()
            if vc:
                reflectance: dict[str, Any] = {"type": "mesh_attribute", "name": "vertex_color"}
            else:
                reflectance = {"type": "rgb", "value": [0.5, 0.5, 0.5]}
            props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": reflectance})
            mesh = mi.Mesh(mid, verts.shape[0], faces.shape[0], props=props, has_vertex_normals=smooth)
            if vc:
                mesh.add_attribute("vertex_color", 3, np.full(verts.shape[0] * 3, 0.5, dtype=np.float32))
            mparams = mi.traverse(mesh)
            _assign(mparams, "vertex_positions", verts.reshape(-1))
            _assign(mparams, "faces", faces.reshape(-1))
            mparams.update()
            scene[mid] = mesh
        self.scene = mi.load_dict(scene)
        self.params = mi.traverse(self.scene)

    def render(
        self,
        meshes: list[tuple[np.ndarray, np.ndarray]],
        albedo: list[np.ndarray],
        vcols: list[np.ndarray | None],
        camera: Camera,
        spp: int,
    ) -> np.ndarray:
        """Updates the scene in place and renders linear RGBA, (H, W, 4) float32."""
        mi, p = self.mi, self.params
        for mid, (verts, _), alb, vc in zip(self.mesh_ids, meshes, albedo, vcols):
            _assign(p, f"{mid}.vertex_positions", verts.reshape(-1))
            if vc is not None:
                _assign(p, f"{mid}.vertex_color", vc.reshape(-1))
            else:
                p[f"{mid}.bsdf.reflectance.value"] = mi.Color3f(*[float(a) for a in alb])
        x_fov, ppx, ppy = _sensor_params(camera)
        p["sensor.to_world"] = mi.AffineTransform4f(_to_world_matrix(camera))
        p["sensor.x_fov"] = x_fov
        p["sensor.principal_point_offset_x"] = ppx
        p["sensor.principal_point_offset_y"] = ppy
        for name, (towards, _) in _LIGHTS.items():
            towards_world = camera.R.T @ (towards / np.linalg.norm(towards))
            p[f"{name}.to_world"] = mi.AffineTransform4f(_directional_to_world(-towards_world))
        p.update()
        image = mi.render(self.scene, spp=spp, seed=0)
        return np.asarray(mi.TensorXf(image).numpy(), dtype=np.float32)


def _topology_key(faces: np.ndarray, n_verts: int) -> tuple[int, int, str]:
    digest = hashlib.blake2b(faces.tobytes(), digest_size=12).hexdigest()
    return (n_verts, faces.shape[0], digest)


def _get_renderer(
    variant: str,
    meshes: list[tuple[np.ndarray, np.ndarray]],
    has_vc: tuple[bool, ...],
    width: int,
    height: int,
    smooth: bool,
) -> _SceneRenderer:
    key = (
        variant,
        tuple(_topology_key(f, v.shape[0]) for v, f in meshes),
        has_vc,
        width,
        height,
        smooth,
    )
    renderer = _SCENE_CACHE.get(key)
    if renderer is None:
        mi = _mitsuba(variant)
        renderer = _SceneRenderer(mi, meshes, has_vc, width, height, smooth)
        _SCENE_CACHE[key] = renderer
        while len(_SCENE_CACHE) > _SCENE_CACHE_SIZE:
            _SCENE_CACHE.popitem(last=False)
    else:
        _SCENE_CACHE.move_to_end(key)
        _mitsuba(variant)
    return renderer


def clear_scene_cache() -> None:
    """Drops all cached Mitsuba scenes (frees their memory)."""
    _SCENE_CACHE.clear()


# --------------------------------------------------------------------------
# Public rendering API
# --------------------------------------------------------------------------


def render_meshes(
    meshes: list[tuple[np.ndarray, np.ndarray]],
    camera: Camera,
    *,
    colors: list[tuple[float, float, float]] | None = None,
    vertex_colors: list[np.ndarray | None] | None = None,
    spp: int = 16,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    variant: str | None = None,
    smooth: bool = True,
) -> np.ndarray:
    """Renders triangle meshes with a clay look from an OpenCV camera.

    Lighting is camera-relative (key light from the upper left, fill from the
    right, constant ambient environment), so any view is readable.  The scene
    is cached per topology; later calls with the same topology and image size
    only update positions/colours/camera in place.

    Args:
        meshes: List of (vertices (V, 3) float, faces (F, 3) int).
        camera: OpenCV camera; its width/height set the image size.
        colors: Optional sRGB albedo per mesh, each (r, g, b) in [0, 1].
            Defaults to ``DEFAULT_PALETTE`` by mesh index.
        vertex_colors: Optional list (one entry per mesh) of (V, 3|4) sRGB
            colours in [0, 1] (float) or uint8, or ``None`` to use ``colors``.
        spp: Samples per pixel (>= 1); rounded up to a power of 4 (4,
            16, 64, ...) as required by the low-discrepancy sampler.
        background: sRGB background colour in [0, 1].
        variant: Mitsuba variant; ``None`` uses :func:`choose_variant`.
        smooth: Interpolate vertex normals (smooth shading) if True, flat
            facets otherwise.

    Returns:
        (H, W, 3) float32 sRGB-encoded image in [0, 1].

    Raises:
        ValueError: On malformed meshes, colours or camera.
        RuntimeError: If no Mitsuba variant can render.
    """
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a blsm.render.Camera, got {type(camera).__name__}.")
    if not meshes:
        raise ValueError("render_meshes() needs at least one (vertices, faces) mesh.")
    if int(spp) < 1:
        raise ValueError(f"spp must be >= 1, got {spp}.")
    clean = [_validate_mesh(i, m) for i, m in enumerate(meshes)]
    n = len(clean)
    if colors is not None and len(colors) != n:
        raise ValueError(f"colors has {len(colors)} entries but there are {n} meshes; give one per mesh.")
    if vertex_colors is not None and len(vertex_colors) != n:
        raise ValueError(
            f"vertex_colors has {len(vertex_colors)} entries but there are {n} meshes; "
            "give one per mesh (None for meshes without vertex colours)."
        )
    palette = DEFAULT_PALETTE
    albedo = [
        srgb_to_linear(
            _as_rgb(colors[i] if colors is not None else palette[i % len(palette)], f"colors[{i}]")
        )
        for i in range(n)
    ]
    vcols: list[np.ndarray | None] = [None] * n
    if vertex_colors is not None:
        vcols = [
            None if vc is None else _validate_vertex_colors(i, vc, clean[i][0].shape[0])
            for i, vc in enumerate(vertex_colors)
        ]
    bg_lin = srgb_to_linear(_as_rgb(background, "background")).astype(np.float32)
    _sensor_params(camera)  # validate intrinsics before touching mitsuba

    variant = _resolve_variant(variant)
    has_vc = tuple(vc is not None for vc in vcols)
    renderer = _get_renderer(variant, clean, has_vc, camera.width, camera.height, smooth)
    spp_eff = max(4, 4 ** math.ceil(math.log(int(spp), 4) - 1e-9))
    rgba = renderer.render(clean, albedo, vcols, camera, spp_eff)
    rgb, alpha = rgba[..., :3], np.clip(rgba[..., 3:4], 0.0, 1.0)
    linear = rgb + (1.0 - alpha) * bg_lin  # film rgb is already alpha-weighted (emitters hidden)
    return linear_to_srgb(linear).astype(np.float32)


def save_png(image: np.ndarray, path: str | os.PathLike[str]) -> Path:
    """Writes an image as PNG atomically (temp file + ``os.replace``).

    Args:
        image: (H, W), (H, W, 3) or (H, W, 4); float in [0, 1] (clipped) or uint8.
        path: Destination path; parent directories are created.

    Returns:
        The destination path.
    """
    from PIL import Image

    arr = np.asarray(image)
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] not in (3, 4)):
        raise ValueError(f"image must have shape (H, W), (H, W, 3) or (H, W, 4), got {arr.shape}.")
    if arr.dtype != np.uint8:
        if not np.issubdtype(arr.dtype, np.floating):
            raise ValueError(f"image must be float in [0, 1] or uint8, got dtype {arr.dtype}.")
        arr = (np.clip(np.nan_to_num(arr), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    from blsm.io import atomic_write

    out = Path(path)
    with atomic_write(out) as fh:
        Image.fromarray(np.ascontiguousarray(arr)).save(fh, format="PNG")
    return out


def _fit_text(draw: Any, text: str, font: Any, max_width: int) -> str:
    if draw.textlength(text, font=font) <= max_width:
        return text
    while text and draw.textlength(text + "...", font=font) > max_width:
        text = text[:-1]
    return text + "..."


def render_grid(
    items: list[list[tuple[np.ndarray, np.ndarray]]],
    out_path: str | os.PathLike[str],
    *,
    labels: list[str] | None = None,
    cols: int,
    tile_size: tuple[int, int] = (192, 256),
    camera_fn: Callable[[list[tuple[np.ndarray, np.ndarray]]], Camera] | None = None,
    colors: list[tuple[float, float, float]] | None = None,
    spp: int = 16,
    variant: str | None = None,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    label_height: int = 18,
    smooth: bool = True,
) -> Path:
    """Renders one tile per item and writes a labelled contact sheet PNG.

    The sheet has ``cols`` columns and ``ceil(len(items) / cols)`` rows; each
    cell is ``tile_size`` plus, when ``labels`` is given, a ``label_height``
    text strip under the tile.  Final size: ``(cols * W, rows * (H + strip))``.
    Tiles with the same mesh topology reuse one loaded scene.

    Args:
        items: One list of (vertices (V, 3), faces (F, 3)) meshes per tile.
        out_path: Destination PNG (written atomically).
        labels: Optional text per item, drawn under its tile.
        cols: Number of columns (>= 1).
        tile_size: (W, H) of each rendered tile in pixels.
        camera_fn: ``camera_fn(item) -> Camera``; defaults to
            :func:`auto_camera` (front view, box fit, 10 deg elevation).  The
            camera's size must equal ``tile_size``.
        colors: Optional sRGB albedo per mesh index within an item.
        spp: Samples per pixel.
        variant: Mitsuba variant; ``None`` uses :func:`choose_variant`.
        background: sRGB background colour (also used for empty cells).
        label_height: Height in pixels of the label strip (only with labels).
        smooth: Smooth (vertex-normal) shading.

    Returns:
        The written path.
    """
    if not items:
        raise ValueError("render_grid() needs at least one item to render.")
    if int(cols) < 1:
        raise ValueError(f"cols must be >= 1, got {cols}.")
    if labels is not None and len(labels) != len(items):
        raise ValueError(f"labels has {len(labels)} entries but there are {len(items)} items.")
    width, height = (int(s) for s in tile_size)
    if width <= 0 or height <= 0:
        raise ValueError(f"tile_size must be positive (W, H), got {tile_size}.")
    bg = _as_rgb(background, "background")
    strip = int(label_height) if labels is not None else 0
    cols = int(cols)
    rows = -(-len(items) // cols)
    cell_h = height + strip
    sheet = np.empty((rows * cell_h, cols * width, 3), dtype=np.float32)
    sheet[:] = bg.astype(np.float32)

    for idx, item in enumerate(items):
        if not item:
            raise ValueError(f"items[{idx}] is empty; each item needs at least one mesh.")
        item_colors = None
        if colors is not None:
            item_colors = [colors[i % len(colors)] for i in range(len(item))]
        camera = camera_fn(item) if camera_fn is not None else auto_camera(item, width, height)
        if (camera.width, camera.height) != (width, height):
            raise ValueError(
                f"camera_fn returned a {camera.width}x{camera.height} camera for items[{idx}] "
                f"but tile_size is {width}x{height}; make them match."
            )
        tile = render_meshes(
            item, camera, colors=item_colors, spp=spp, background=tuple(bg), variant=variant, smooth=smooth
        )
        r, c = divmod(idx, cols)
        sheet[r * cell_h : r * cell_h + height, c * width : (c + 1) * width] = tile

    image = (np.clip(sheet, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if labels is not None and strip > 0:
        from PIL import Image, ImageDraw, ImageFont

        pil = Image.fromarray(image)
        draw = ImageDraw.Draw(pil)
        try:
            font = ImageFont.load_default(size=max(8, strip - 6))
        except TypeError:  # Pillow < 10.1 has no size argument
            font = ImageFont.load_default()
        text_rgb = (30, 30, 30) if bg.mean() > 0.5 else (230, 230, 230)
        for idx, label in enumerate(labels):
            r, c = divmod(idx, cols)
            text = _fit_text(draw, str(label), font, width - 4)
            x0 = c * width + width / 2.0
            y0 = r * cell_h + height + strip / 2.0
            draw.text((x0, y0), text, fill=text_rgb, font=font, anchor="mm")
        image = np.asarray(pil)
    return save_png(image, out_path)
