"""Mitsuba 3 set-up shared by the renderers: variant choice, OpenCV-camera sensors, the environment.

Mitsuba is imported lazily: importing this module never imports mitsuba nor sets a variant (the
entry point chooses the variant once).  :func:`choose_variant` probes candidates in a subprocess,
because ``llvm_ad_rgb`` aborts the whole process ("LLVM ERROR: Cannot select ... fminimum") on
machines with libLLVM 15; :func:`resolve_variant` validates a given one and :func:`load_mitsuba`
imports mitsuba and activates it.

:func:`to_world_matrix` and :func:`sensor_params` turn a :class:`blsm.camera.Camera` (OpenCV: x
right, y down, z forward; ``K``, ``R``, ``t`` world to camera; pixel centres at integer + 0.5)
into the ``to_world``, ``x_fov`` and principal point offsets of Mitsuba's ``perspective``
sensor, for a film of the camera's width and height. :func:`perspective_sensor` is the sensor and
film of every renderer (:mod:`blsm.render`, :mod:`synth.render`), and :func:`set_camera` points a
loaded one at a camera. :func:`env_rotation` is the rotation of an environment map about +Y, the
one the renderers give Mitsuba's ``envmap`` and the one :mod:`synth.ground` looks it up with.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np

from blsm.camera import Camera

__all__ = [
    "DEFAULT_VARIANTS",
    "VARIANT_ENV",
    "choose_variant",
    "env_rotation",
    "load_mitsuba",
    "perspective_sensor",
    "probe_variant",
    "resolve_variant",
    "sensor_params",
    "set_camera",
    "to_world_matrix",
]

VARIANT_ENV = "BLSM_MITSUBA_VARIANT"
"""Environment variable that forces a Mitsuba variant (still probed)."""

DEFAULT_VARIANTS: tuple[str, ...] = ("llvm_ad_rgb", "scalar_rgb")
"""Variants :func:`choose_variant` tries by default, best first."""

_PROBE_TIMEOUT_S = 180.0

# Per-process caches (filled lazily).
_CHOSEN_VARIANT: dict[tuple[str, ...], str] = {}
_PROBE_RESULTS: dict[str, tuple[bool, str]] = {}

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


def probe_variant(variant: str, timeout: float = _PROBE_TIMEOUT_S) -> tuple[bool, str]:
    """Checks in a subprocess that ``variant`` can load and render a scene.

    The subprocess renders an 8x8 image of one triangle, so a hard abort inside LLVM cannot kill
    the caller.  The result is cached per variant for the lifetime of the process.

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


def choose_variant(preferred: tuple[str, ...] = DEFAULT_VARIANTS) -> str:
    """Returns the first Mitsuba variant from ``preferred`` that actually works.

    Each candidate is probed in a subprocess (:func:`probe_variant`: load + render a tiny
    triangle scene) so that a hard abort inside LLVM cannot kill the caller.  The result
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
        ok, reason = probe_variant(variant)
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


def resolve_variant(variant: str | None) -> str:
    """Returns a variant that can render: ``variant`` after probing it, or :func:`choose_variant`.

    Args:
        variant: A Mitsuba variant name, or ``None`` to choose one from :data:`DEFAULT_VARIANTS`
            (or ``$BLSM_MITSUBA_VARIANT``).

    Returns:
        The variant name.

    Raises:
        RuntimeError: If ``variant`` (or every default candidate) cannot render here.
    """
    if variant is None:
        return choose_variant()
    ok, reason = probe_variant(variant)
    if not ok:
        raise RuntimeError(
            f"Mitsuba variant {variant!r} cannot render on this machine: {reason}. "
            "Pass variant=None to pick a working one automatically."
        )
    return variant


def load_mitsuba(variant: str) -> Any:
    """Imports mitsuba and activates ``variant`` (only if not already active).

    Args:
        variant: A Mitsuba variant name, e.g. from :func:`resolve_variant`.

    Returns:
        The ``mitsuba`` module, with ``variant`` set.
    """
    import mitsuba as mi

    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi


# --------------------------------------------------------------------------
# OpenCV camera -> Mitsuba perspective sensor
# --------------------------------------------------------------------------


def to_world_matrix(camera: Camera) -> np.ndarray:
    """Mitsuba sensor ``to_world`` reproducing an OpenCV camera's pose.

    Mitsuba's sensor looks along local +Z with +Y up and +X to the *left* of
    the image, i.e. its local axes are OpenCV's (-x, -y, +z).

    Args:
        camera: OpenCV camera (x right, y down, z forward; ``R, t`` world to camera).

    Returns:
        (4, 4) float64 camera-to-world matrix (translation in metres) for
        ``mi.AffineTransform4f``.
    """
    c2w = np.eye(4)
    c2w[:3, :3] = camera.R.T
    c2w[:3, 3] = camera.center
    c2w[:3, 0] *= -1.0
    c2w[:3, 1] *= -1.0
    return c2w


def sensor_params(camera: Camera) -> tuple[float, float, float]:
    """Field of view and principal point of Mitsuba's ``perspective`` sensor for an OpenCV ``K``.

    For a sensor with ``fov_axis="x"`` and a film of ``camera.width x camera.height`` pixels,
    rays then pass through the same pixels as :meth:`blsm.camera.Camera.project` (pixel centres
    at integer + 0.5).

    Args:
        camera: OpenCV camera with square pixels and no skew (``K[0, 0] == K[1, 1]``,
            ``K[0, 1] == 0``).

    Returns:
        ``(x_fov, principal_point_offset_x, principal_point_offset_y)``: the horizontal field of
        view in degrees and the principal point's offsets from the film centre, as fractions of
        the film width and height in Mitsuba's sign convention.

    Raises:
        ValueError: On non-positive focal lengths, non-square pixels or skew.
    """
    K = camera.K
    fx, fy = K[0, 0], K[1, 1]
    if fx <= 0 or fy <= 0:
        raise ValueError(f"Camera focal lengths must be positive, got fx={fx}, fy={fy}.")
    if abs(fx - fy) > 1e-6 * max(fx, fy) or abs(K[0, 1]) > 1e-9:
        raise ValueError(
            "Mitsuba's perspective sensor supports square pixels without skew only "
            "(K[0,0] == K[1,1], K[0,1] == 0); "
            "rescale the image or the intrinsics first."
        )
    x_fov = math.degrees(2.0 * math.atan(0.5 * camera.width / fx))
    # Offsets are fractions of the film size measured from the film centre;
    # Mitsuba's sign is opposite to the OpenCV pixel axes (checked by tests).
    ppx = -(K[0, 2] - 0.5 * camera.width) / camera.width
    ppy = -(K[1, 2] - 0.5 * camera.height) / camera.height
    return float(x_fov), float(ppx), float(ppy)


def perspective_sensor(width: int, height: int, sampler: dict[str, Any], pixel_format: str = "rgba") -> dict[str, Any]:
    """The ``perspective`` sensor of every renderer, as a dict for ``mi.load_dict``.

    A placeholder view (40 degrees across x, near clip 0.01 m, far clip 1000 m) that
    :func:`set_camera` replaces with an OpenCV camera's, and an ``hdrfilm`` of ``width`` x
    ``height`` pixels with a box filter: each sample stays in its own pixel, so no splatting races
    between threads and the image is bit-reproducible (and 4x faster than a gaussian filter).

    Args:
        width, height: the film, pixels.
        sampler: the sampler's dict (e.g. ``{"type": "independent", "sample_count": 16}``).
        pixel_format: the film's channels: ``rgba`` gives antialiased coverage (alpha), ``rgb``
            none.
    """
    return {
        "type": "perspective",
        "fov": 40.0,
        "fov_axis": "x",
        "near_clip": 0.01,
        "far_clip": 1000.0,
        "sampler": sampler,
        "film": {
            "type": "hdrfilm",
            "width": width,
            "height": height,
            "pixel_format": pixel_format,
            "rfilter": {"type": "box"},
        },
    }


def set_camera(mi: Any, params: Any, name: str, camera: Camera, scalar: Callable[[float], Any] = float) -> None:
    """Point the loaded :func:`perspective_sensor` ``name`` of a scene's ``params``
    (``mi.traverse(scene)``) at an OpenCV ``camera``; the caller calls ``params.update()``.

    Args:
        mi: the mitsuba module, its variant set.
        params: the scene's parameters.
        name: the sensor's id in the scene.
        camera: the camera (its size must be the film's).
        scalar: wraps the field of view and the principal point's offsets; ``dr.opaque`` keeps
            them out of compiled kernels as literals, so a new camera compiles nothing.
    """
    x_fov, ppx, ppy = sensor_params(camera)
    params[f"{name}.to_world"] = mi.AffineTransform4f(to_world_matrix(camera))
    params[f"{name}.x_fov"] = scalar(x_fov)
    params[f"{name}.principal_point_offset_x"] = scalar(ppx)
    params[f"{name}.principal_point_offset_y"] = scalar(ppy)


def env_rotation(angle: float) -> np.ndarray:
    """(3, 3) float64 rotation by ``angle`` radians about +Y: an environment map's ``to_world``.

    The renderers give it to Mitsuba's ``envmap`` (as the upper left of a 4 x 4 transform);
    :func:`synth.ground.env_lookup` looks the map up through it, so the two agree.
    """
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
