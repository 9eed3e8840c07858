"""Backgrounds and lighting: HDRI folders, backplate image folders, and an embedded procedural sky.

- ``hdri``: a folder of latitude-longitude environment maps (``.exr``, ``.hdr``), read and resized
  with OpenImageIO. The environment is visible behind the people and lights them; each image draws
  a rotation about +Y and an exposure. Maps are normalised to a mean luminance of ``MEAN_LUMINANCE`` first, so one
  exposure range suits every file.
- ``images``: a folder of backplates (``.jpg``, ``.jpeg``, ``.png``, ``.exr``, ``.hdr``, ``.tif``);
  each image draws one, crops it to the image's aspect at a random place and resizes it (OpenImageIO).
  People are lit by the procedural sky (hidden) and composited over the plate with the render's
  anti-aliased coverage.
- ``default``: the embedded procedural sky (no files): a sky gradient, a sun and a ground plane
  colour, drawn per image.

Bad input (a missing or empty folder, an unreadable file) is a ValueError naming the path.
:func:`check_files` opens and decodes every file of a run before any work starts: an empty,
truncated or undecodable file, one smaller than ``MIN_SIDE`` px a side (a 1 x 1 placeholder) or
larger than ``MAX_PIXELS`` (a decompression bomb), NaN or inf pixels, or a black HDRI.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import sys
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

HDRI_EXT = (".exr", ".hdr")
IMAGE_EXT = (".jpg", ".jpeg", ".png", ".exr", ".hdr", ".tif", ".tiff")
KINDS = ("default", "hdri", "images")
_LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
MEAN_LUMINANCE = 0.4  # environments are scaled to this mean luminance before the exposure draw
MIN_SIDE = 16  # pixels: a smaller background is a placeholder or a mistake, not a picture
MAX_PIXELS = 1 << 28  # 268 M pixels (16384 x 16384): 3 GiB as float RGB once decoded


def list_folder(
    folder: str | Path, exts: tuple[str, ...], what: str, only: Sequence[str] = (), exclude: Sequence[str] = ()
) -> list[Path]:
    """Sorted files of ``folder`` with one of ``exts``, restricted to the names in ``only`` (when
    given) and without those in ``exclude``; an error when there is none or a name is not there."""
    folder = Path(folder).expanduser()
    if not folder.is_dir():
        raise ValueError(f"{folder}: no such {what} folder")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in exts and p.is_file())
    names = {p.name for p in files}
    unknown = [n for n in (*only, *exclude) if n not in names]
    if unknown:
        raise ValueError(f"{folder}: no {what} file named {unknown[0]!r} (files: {sorted(names)})")
    if only:
        files = [p for p in files if p.name in only]
    files = [p for p in files if p.name not in exclude]
    if not files:
        raise ValueError(f"{folder}: the {what} folder holds no {'/'.join(exts)} files (after files/exclude)")
    return files


@contextlib.contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Silence file descriptor 2 (libpng and OpenImageIO print their own error lines there); the
    errors still reach the caller through ``geterror()``."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no real stderr (embedded): nothing to silence
        yield
        return
    try:
        with tempfile.TemporaryFile() as sink:
            os.dup2(sink.fileno(), 2)
            try:
                yield
            finally:
                os.dup2(saved, 2)
    finally:
        os.close(saved)


def read_image(path: str | Path, width: int | None = None, height: int | None = None) -> np.ndarray:
    """Read an image with OpenImageIO as (H, W, 3) float32 linear RGB, optionally resized.

    8-bit and 16-bit files are taken as sRGB-encoded and linearised; float files are linear. The
    whole file is decoded: a truncated or corrupt one is an error (a ValueError naming it), as is
    one under ``MIN_SIDE`` or over ``MAX_PIXELS``.
    """
    import OpenImageIO as oiio

    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the image ({exc.strerror})") from None
    if size == 0:
        raise ValueError(f"{path}: empty file (0 bytes)")
    with _quiet_stderr():
        inp = oiio.ImageInput.open(str(path))
        if inp is None:
            raise ValueError(f"{path}: not a readable image ({_first_line(oiio.geterror()) or 'unknown format'})")
        try:
            spec = inp.spec()
            if min(spec.width, spec.height) < MIN_SIDE:
                raise ValueError(f"{path}: image is {spec.width}x{spec.height} px, under the minimum of {MIN_SIDE} px a side")
            if spec.width * spec.height > MAX_PIXELS:
                raise ValueError(f"{path}: image is {spec.width}x{spec.height} px, over the limit of {MAX_PIXELS} pixels")
            px = inp.read_image(0, 0, 0, min(spec.nchannels, 3), "float")
            err = inp.geterror()
        finally:
            inp.close()
    if px is None or err:
        raise ValueError(f"{path}: corrupt or truncated image ({_first_line(err) or 'no pixels'})")
    px = np.asarray(px, dtype=np.float32)
    if not np.isfinite(px).all():
        raise ValueError(f"{path}: the image has NaN or inf pixels")
    if width is not None and height is not None and (spec.width, spec.height) != (width, height):
        # Resized from the file's own buffer (in its pixel format), as datasets were always made.
        with _quiet_stderr():
            buf = oiio.ImageBufAlgo.resize(oiio.ImageBuf(str(path)), roi=oiio.ROI(0, width, 0, height, 0, 1, 0, spec.nchannels))
            resized = buf.get_pixels(oiio.FLOAT)
            err = buf.geterror()
        if resized is None or err:
            raise ValueError(f"{path}: corrupt or truncated image ({_first_line(err) or 'no pixels'})")
        return _linear_rgb(path, np.asarray(resized, dtype=np.float32), spec)
    return _linear_rgb(path, px, spec)


def _linear_rgb(path: Path, px: np.ndarray, spec: Any) -> np.ndarray:
    """Decoded pixels to (H, W, 3) float32 linear RGB (grey repeated, alpha dropped)."""
    import OpenImageIO as oiio

    if px.ndim == 2:
        px = px[..., None]
    if px.shape[-1] == 1:
        px = np.repeat(px, 3, axis=-1)
    if px.shape[-1] == 2:  # grey + alpha
        px = np.repeat(px[..., :1], 3, axis=-1)
    px = px[..., :3]
    if not np.isfinite(px).all():
        raise ValueError(f"{path}: the image has NaN or inf pixels")
    if spec.format.basetype in (oiio.UINT8, oiio.UINT16) or spec.get_string_attribute("oiio:ColorSpace") == "sRGB":
        px = np.where(px <= 0.04045, px / 12.92, ((np.clip(px, 0, None) + 0.055) / 1.055) ** 2.4)
    return np.ascontiguousarray(px, dtype=np.float32)


def _first_line(text: str) -> str:
    return text.strip().splitlines()[0] if text.strip() else ""


def check_files(files: Sequence[Path], kind: str, env_width: int) -> None:
    """Open and decode every background file of a run (``kind`` hdri or images), as the workers
    will; raise a ValueError naming the first bad one (see the module docstring)."""
    for f in files:
        if kind == "hdri":
            load_hdri(f, env_width)
        else:
            read_image(f)


def load_hdri(path: str | Path, width: int) -> np.ndarray:
    """An environment map resized to (width / 2, width), normalised to ``MEAN_LUMINANCE``."""
    env = read_image(path, width, width // 2)
    env = np.clip(env, 0.0, None)
    # Solid-angle weights of the rows of a latitude-longitude map.
    theta = (np.arange(env.shape[0]) + 0.5) / env.shape[0] * math.pi
    w = np.sin(theta)[:, None]
    mean = float((env @ _LUMA * w).sum() / (w.sum() * env.shape[1]))
    if mean <= 0:
        raise ValueError(f"{path}: the environment map is black")
    return (env * (MEAN_LUMINANCE / mean)).astype(np.float32)


def crop_backplate(image: np.ndarray, width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    """A random crop of ``image`` at the target aspect (at least 60 % of the shorter side), resized."""
    h, w = image.shape[:2]
    aspect = width / height
    ch = int(min(h, w / aspect) * rng.uniform(0.6, 1.0))
    cw = max(1, int(round(ch * aspect)))
    ch = max(1, ch)
    y0 = int(rng.integers(0, h - ch + 1))
    x0 = int(rng.integers(0, w - cw + 1))
    return _resized(image[y0 : y0 + ch, x0 : x0 + cw], width, height)


def _resized(crop: np.ndarray, width: int, height: int) -> np.ndarray:
    """``crop`` resized to ``width x height`` (OpenImageIO's default filter), float32 (H, W, 3)."""
    import OpenImageIO as oiio

    out = oiio.ImageBufAlgo.resize(oiio.ImageBuf(np.ascontiguousarray(crop)), roi=oiio.ROI(0, width, 0, height, 0, 1, 0, 3))
    return np.asarray(out.get_pixels(oiio.FLOAT), dtype=np.float32).reshape(height, width, 3)


PLATES_JSON = "plates.json"
"""A backplate folder's optional description: ``{"file.jpg": {"horizon": 0.45, ...}, ...}``, the row
of the photograph's horizon (its eye level: the vanishing line of the ground) as a fraction of the
image height from the top, or null where no ground a person could stand on is seen
(``scripts/setup_backplates.py`` writes one for the bank it installs)."""


def read_horizons(folder: str | Path) -> dict[str, float]:
    """The horizons of ``folder``'s ``plates.json`` by file name (files without one left out); {}
    without the file. A ValueError names the file when it is not such a JSON object."""
    path = Path(folder).expanduser() / PLATES_JSON
    if not path.is_file():
        return {}
    try:
        plates = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not readable JSON ({exc})") from None
    if not isinstance(plates, dict):
        raise ValueError(f"{path}: expected an object {{\"file\": {{\"horizon\": fraction or null}}}}")
    out = {}
    for name, info in plates.items():
        hz = info.get("horizon") if isinstance(info, dict) else None
        if hz is None:
            continue
        if not isinstance(hz, (int, float)) or not 0.0 <= hz <= 1.0:
            raise ValueError(f"{path}: {name!r} has horizon {hz!r}; expected a fraction of the height in [0, 1] or null")
        out[name] = float(hz)
    return out


def horizon_row(K: np.ndarray, R: np.ndarray) -> float | None:
    """The image row where the horizon (directions with world ``y = 0``) crosses the principal
    point's column, or None when the camera is not upright (looking nearly straight down or up,
    or upside down): ``v = cy - fy R[2, 1] / R[1, 1]`` (OpenCV camera, Y-up world)."""
    if R[1, 1] > -0.3:
        return None
    return float(K[1, 2] - K[1, 1] * R[2, 1] / R[1, 1])


def crop_backplate_at_horizon(image: np.ndarray, horizon: float, width: int, height: int, row: float,
                              rng: np.random.Generator) -> np.ndarray | None:
    """A crop of ``image`` at the target aspect, resized, whose horizon (``horizon`` of its height)
    lands on image row ``row``: the camera's own horizon, so that the people's ground plane meets
    the photograph's ground at eye level. The crop is as large as the horizon allows, times a
    factor uniform in [0.6, 1] (at least 25 % of the plate's shorter side); None when no such crop
    fits in the plate."""
    h, w = image.shape[:2]
    aspect = width / height
    hz, t = horizon * h, row / height  # plate pixels; the horizon's place in the output, 0 top .. 1 bottom
    full = min(h, w / aspect)
    limits = [full]
    if t > 0:
        limits.append(hz / t)
    if t < 1:
        limits.append((h - hz) / (1 - t))
    top = min(limits)
    if top < 0.25 * full or top < 8:
        return None
    ch = int(top * rng.uniform(0.6, 1.0))
    cw = max(1, int(round(ch * aspect)))
    y0 = min(max(int(round(hz - t * ch)), 0), h - ch)  # whole plate pixels: the horizon within one of them
    x0 = int(rng.integers(0, w - cw + 1))
    return _resized(image[y0:y0 + ch, x0:x0 + cw], width, height)


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
    mean = float(((env @ _LUMA) * theta_w).sum(dtype=np.float64) / (theta_w.sum(dtype=np.float64) * width))
    params = {"sun_elevation_deg": math.degrees(sun_el), "sun_azimuth_deg": math.degrees(sun_az)}
    return (env * f32(MEAN_LUMINANCE / mean)).astype(np.float32), params


@dataclass
class Background:
    """What one image uses behind and around the people."""

    kind: str
    env: np.ndarray
    rotation: float
    scale: float
    backplate: np.ndarray | None
    info: dict
