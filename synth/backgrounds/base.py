"""What every background kind gives an image (:class:`Background`) and must do (:class:`BackgroundKind`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
MEAN_LUMINANCE = 0.4  # environments are scaled to this mean luminance before the exposure draw


@dataclass
class Background:
    """What one image uses behind and around the people."""

    kind: str
    env: np.ndarray
    rotation: float
    scale: float
    backplate: np.ndarray | None
    info: dict


class BackgroundKind(Protocol):
    """One kind of ``background.kind``: a module of :mod:`synth.backgrounds` and one line of its
    ``KINDS``. ``cfg`` is the config's ``background`` section (:class:`synth.config.BackgroundConfig`).

    Attributes:
        name: the config's ``background.kind``.
        needs_folder: reads files from ``background.folder`` (``files`` and ``exclude`` apply).
        follows_cameras: can be seen by a moving camera of a sequence (a photograph cannot).
    """

    name: str
    needs_folder: bool
    follows_cameras: bool

    def check(self, cfg: Any) -> None:
        """Decode every file a run of ``cfg`` will read, as the workers will, before any work: a
        ValueError names the first bad one."""

    def open(self, cfg: Any) -> Any:
        """A worker's state for :meth:`draw` (its files, caches)."""

    def draw(self, state: Any, cfg: Any, rng: np.random.Generator, camera: Any, size: tuple[int, int],
             rotation: float, scale: float) -> Background:
        """One image's background: ``size`` (width, height) pixels, ``camera`` the image's, the
        environment's ``rotation`` (radians about +Y) and exposure ``scale`` already drawn."""

    def records(self, cfg: Any) -> set[str]:
        """Keys of ``cfg`` the manifest records beyond kind, folder, files, exclude, exposure_ev and
        env_width (a key that changes nothing for this kind and folder is left out, so runs made
        before it resume)."""
