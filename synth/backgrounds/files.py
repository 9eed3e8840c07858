"""Background files: folders of HDRIs and backplates listed, and images read as linear RGB with
OpenImageIO, every bad file a ValueError naming it (an empty, truncated or undecodable file, one
smaller than ``MIN_SIDE`` px a side (a 1 x 1 placeholder) or larger than ``MAX_PIXELS`` (a
decompression bomb), NaN or inf pixels)."""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

HDRI_EXT = (".exr", ".hdr")
IMAGE_EXT = (".jpg", ".jpeg", ".png", ".exr", ".hdr", ".tif", ".tiff")
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


def resize_image(crop: np.ndarray, width: int, height: int) -> np.ndarray:
    """``crop`` resized to ``width x height`` (OpenImageIO's default filter), float32 (H, W, 3)."""
    import OpenImageIO as oiio

    out = oiio.ImageBufAlgo.resize(oiio.ImageBuf(np.ascontiguousarray(crop)), roi=oiio.ROI(0, width, 0, height, 0, 1, 0, 3))
    return np.asarray(out.get_pixels(oiio.FLOAT), dtype=np.float32).reshape(height, width, 3)
