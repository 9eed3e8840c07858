"""Monte Carlo denoising of rendered images with Intel Open Image Denoise (OIDN).

OIDN is the denoiser of Blender Cycles; PyPI ``pyoidn`` (MIT) binds it and ships the library
(Apache-2.0) with its trained weights, so nothing is downloaded. The path tracer's image is
denoised with the two auxiliary images OIDN's ``RT`` filter is trained with, rendered by the same
samples as the colour (:class:`synth.render.PeopleRenderer` nests the path tracer in Mitsuba's
``aov`` integrator):

- **albedo**: the first hit's diffuse reflectance, linear, in [0, 1]. Where a camera ray sees the
  environment directly it is the environment's radiance clamped to [0, 1] (OIDN's convention for
  emitters), so the backdrop's detail is kept;
- **normal**: the first hit's shading normal (world frame), 0 where nothing is hit.

Both are noisy at the edges of the people (a pixel's samples hit the person or the backdrop), so
``cleanAux`` stays off and OIDN prefilters them. The colour is HDR (``hdr``). Labels never pass
through here: they come from the separate pixel-centre label pass, so denoising changes pixels of
the RGB only.

One :class:`Denoiser` per process holds an OIDN CPU device with a fixed thread count (a generator
worker's share of the cores) and one filter, committed again only when the image size changes.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np


class DenoiseError(RuntimeError):
    """OIDN reported an error."""


class Denoiser:
    """OIDN's ``RT`` filter on the CPU.

    Args:
        threads: CPU threads OIDN uses (0: all).
        quality: ``high`` (the default), ``balanced`` or ``fast``.
    """

    def __init__(self, threads: int = 1, quality: str = "high") -> None:
        try:
            import pyoidn
        except ImportError as exc:  # pragma: no cover - a dependency of the package
            raise DenoiseError(f"denoising needs pyoidn ({exc}); pip install pyoidn, or set render.denoise: false") from None
        self._oidn = pyoidn
        qualities = {"high": pyoidn.OIDN_QUALITY_HIGH, "balanced": pyoidn.OIDN_QUALITY_BALANCED,
                     "fast": pyoidn.OIDN_QUALITY_FAST}  # fmt: skip
        if quality not in qualities:
            raise ValueError(f"denoise quality must be one of {sorted(qualities)}, got {quality!r}")
        self.device = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
        self.device.set_int("numThreads", int(threads))
        self.device.commit()
        self._check("device")
        self.filter = pyoidn.Filter(self.device, pyoidn.OIDN_FILTER_TYPE_RT)
        self.filter.set_bool("hdr", True)
        self.filter.set_bool("cleanAux", False)
        self.filter.set_quality(qualities[quality])
        self._check("filter")
        self._shape: tuple[int, int] | None = None
        self._bufs: dict[str, np.ndarray] = {}

    def _check(self, what: str) -> None:
        msg = self.device.get_error()
        if msg is not None:
            raise DenoiseError(f"Open Image Denoise ({what}): {msg}")

    def __call__(self, color: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """Denoise ``color`` (H, W, 3) linear HDR with ``albedo`` and ``normal`` (H, W, 3); a new array."""
        o = self._oidn
        shape = color.shape[:2]
        if color.shape != (*shape, 3) or albedo.shape != color.shape or normal.shape != color.shape:
            raise ValueError(f"color, albedo and normal must be (H, W, 3) alike, got {color.shape}, {albedo.shape}, {normal.shape}")
        if shape != self._shape:
            # The filter keeps pointers to these arrays: bind them once per size, then fill in place.
            self._bufs = {k: np.zeros((*shape, 3), np.float32) for k in ("color", "albedo", "normal", "output")}
            for key, name in (("color", o.OIDN_IMAGE_COLOR), ("albedo", o.OIDN_IMAGE_ALBEDO),
                              ("normal", o.OIDN_IMAGE_NORMAL), ("output", o.OIDN_IMAGE_OUTPUT)):  # fmt: skip
                self.filter.set_image(name, self._bufs[key], o.OIDN_FORMAT_FLOAT3)
            self.filter.commit()
            self._check("commit")
            self._shape = shape
        np.copyto(self._bufs["color"], np.maximum(color, 0.0), casting="same_kind")
        np.copyto(self._bufs["albedo"], np.clip(albedo, 0.0, 1.0), casting="same_kind")
        np.copyto(self._bufs["normal"], np.clip(normal, -1.0, 1.0), casting="same_kind")
        self.filter.execute()
        self._check("execute")
        return self._bufs["output"].copy()

    def close(self) -> None:
        self.filter.release()
        self.device.release()

    def __del__(self) -> None:  # pragma: no cover - best effort at exit
        try:
            self.close()
        except Exception:
            pass


@functools.lru_cache(maxsize=2)
def shared_denoiser(threads: int = 1, quality: str = "high") -> Denoiser:
    """One :class:`Denoiser` per process and setting (an OIDN device loads its weights once, about
    a second; the renderers of one worker share it)."""
    return Denoiser(threads=threads, quality=quality)


def denoise_inputs(image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Split a render of the ``aov`` integrator nesting the path tracer (channels R, G, B, A,
    albedo RGB, normal XYZ) into colour, alpha, albedo and normal, with OIDN's albedo for
    pixels that see the environment (module docstring)."""
    if image.ndim != 3 or image.shape[2] != 10:
        raise ValueError(f"expected (H, W, 10) channels RGBA + albedo + normal, got {image.shape}")
    color, alpha = image[..., :3], np.clip(image[..., 3], 0.0, 1.0)
    albedo, normal = image[..., 4:7], image[..., 7:10]
    # The film weights the albedo AOV by the hit fraction; the environment's share is the radiance.
    albedo = albedo + (1.0 - alpha[..., None]) * np.clip(color, 0.0, 1.0)
    return color, alpha, albedo.astype(np.float32), normal.astype(np.float32)


def psnr(image: np.ndarray, reference: np.ndarray, peak: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB of ``image`` against ``reference`` (same shape)."""
    mse = float(np.mean((np.asarray(image, np.float64) - np.asarray(reference, np.float64)) ** 2))
    return float("inf") if mse == 0.0 else 10.0 * np.log10(peak**2 / mse)


__all__: list[Any] = ["Denoiser", "DenoiseError", "denoise_inputs", "psnr", "shared_denoiser"]
