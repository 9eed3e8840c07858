"""Clay-style rendering of triangle meshes with Mitsuba 3.

Conventions: metres, Y up, bodies face +Z at rest.  Cameras are
:class:`blsm.camera.Camera`, the OpenCV pinhole model: camera axes x right,
y down, z forward; ``K`` is 3x3 and ``R, t`` map world to camera
(``X_cam = R @ X_world + t``); pixel centres sit at integer + 0.5, so a
centred camera has its principal point at ``(W / 2, H / 2)``.

Mitsuba is imported lazily: importing this module never imports mitsuba nor
sets a variant.  The variant is chosen by
:func:`blsm.mitsuba_util.choose_variant` (``variant=None``), which probes
candidates in a subprocess.

Rendered images are returned as sRGB-encoded float32 in ``[0, 1]`` (ready to
save).  All colour inputs (``colors``, ``vertex_colors``, ``background``) are
likewise sRGB-encoded values in ``[0, 1]``; they are linearised internally
(:mod:`blsm.color`).

The film is ``rgba`` (rather than ``rgb``) with emitters hidden, so the
alpha channel gives antialiased coverage and the background colour is
composited exactly in linear space.  Lighting uses the ``direct`` integrator
with camera-relative directional key/fill lights plus a weak constant
environment, and a low-discrepancy sampler to keep noise low at 16 spp.

Scenes are cached per (variant, mesh topology, film size, vertex-colour
layout).  Rendering a new frame with the same topology only updates vertex
positions, colours, the sensor and the camera-relative lights through
``mi.traverse(scene)`` + ``params.update()`` instead of reloading the scene.

``Camera``, ``look_at_camera``, ``auto_camera`` and ``choose_variant`` are
re-exported here for older callers; new code imports them from
:mod:`blsm.camera` and :mod:`blsm.mitsuba_util`.
"""

from __future__ import annotations

import hashlib
import math
import os
from collections import OrderedDict
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from blsm.camera import Camera, Mesh, auto_camera, look_at_camera
from blsm.color import linear_to_srgb, srgb_to_linear
from blsm.mitsuba_util import (
    choose_variant,
    load_mitsuba,
    perspective_sensor,
    resolve_variant,
    sensor_params,
    set_camera,
)

__all__ = [
    "DEFAULT_PALETTE",
    "clear_scene_cache",
    "render_grid",
    "render_meshes",
    "save_png",
    # Re-exported for backward compatibility (their home is blsm.camera / blsm.mitsuba_util).
    "Camera",
    "auto_camera",
    "choose_variant",
    "look_at_camera",
]

RGB = tuple[float, float, float]

DEFAULT_PALETTE: tuple[RGB, ...] = (
    (0.78, 0.70, 0.62),  # clay
    (0.55, 0.68, 0.85),  # blue
    (0.62, 0.80, 0.58),  # green
    (0.88, 0.62, 0.55),  # red
    (0.80, 0.74, 0.50),  # yellow
    (0.72, 0.62, 0.82),  # purple
)
"""Default sRGB albedo per mesh index within a scene."""

_SCENE_CACHE_SIZE = 8

# Module-level cache (filled lazily).
_SCENE_CACHE: OrderedDict[tuple[Any, ...], _SceneRenderer] = OrderedDict()


# --------------------------------------------------------------------------
# Colour helpers
# --------------------------------------------------------------------------


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
            # Low-discrepancy samples stratify light selection: ~4x less noise than "independent"
            # at the same spp and cost. The film is rgba (not rgb): the alpha channel gives
            # antialiased coverage so the background can be composited exactly.
            "sensor": perspective_sensor(width, height, {"type": "ldsampler", "sample_count": 4}, "rgba"),
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
        set_camera(mi, p, "sensor", camera)
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
        mi = load_mitsuba(variant)
        renderer = _SceneRenderer(mi, meshes, has_vc, width, height, smooth)
        _SCENE_CACHE[key] = renderer
        while len(_SCENE_CACHE) > _SCENE_CACHE_SIZE:
            _SCENE_CACHE.popitem(last=False)
    else:
        _SCENE_CACHE.move_to_end(key)
        load_mitsuba(variant)
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
        variant: Mitsuba variant; ``None`` uses :func:`blsm.mitsuba_util.choose_variant`.
        smooth: Interpolate vertex normals (smooth shading) if True, flat
            facets otherwise.

    Returns:
        (H, W, 3) float32 sRGB-encoded image in [0, 1].

    Raises:
        ValueError: On malformed meshes, colours or camera.
        RuntimeError: If no Mitsuba variant can render.
    """
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a blsm.camera.Camera, got {type(camera).__name__}.")
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
    sensor_params(camera)  # validate intrinsics before touching mitsuba

    variant = resolve_variant(variant)
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
            :func:`blsm.camera.auto_camera` (front view, box fit, 10 deg elevation).  The
            camera's size must equal ``tile_size``.
        colors: Optional sRGB albedo per mesh index within an item.
        spp: Samples per pixel.
        variant: Mitsuba variant; ``None`` uses :func:`blsm.mitsuba_util.choose_variant`.
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
