"""``background.kind: hdri``: a folder of latitude-longitude environment maps (``.exr``, ``.hdr``),
read and resized with OpenImageIO. The environment is visible behind the people and lights them;
each image draws a file, a rotation about +Y and an exposure. Maps are normalised to a mean
luminance of ``MEAN_LUMINANCE`` first, so one exposure range suits every file; a black map is an
error."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from synth.backgrounds.base import LUMA, MEAN_LUMINANCE, Background
from synth.backgrounds.files import HDRI_EXT, list_folder, read_image


def load_hdri(path: str | Path, width: int) -> np.ndarray:
    """An environment map resized to (width / 2, width), normalised to ``MEAN_LUMINANCE``."""
    env = read_image(path, width, width // 2)
    env = np.clip(env, 0.0, None)
    # Solid-angle weights of the rows of a latitude-longitude map.
    theta = (np.arange(env.shape[0]) + 0.5) / env.shape[0] * math.pi
    w = np.sin(theta)[:, None]
    mean = float((env @ LUMA * w).sum() / (w.sum() * env.shape[1]))
    if mean <= 0:
        raise ValueError(f"{path}: the environment map is black")
    return (env * (MEAN_LUMINANCE / mean)).astype(np.float32)


class Hdri:
    """The kind ``hdri`` (:class:`synth.backgrounds.base.BackgroundKind`)."""

    name, needs_folder, follows_cameras = "hdri", True, True

    def files(self, cfg: Any) -> list[Path]:
        return list_folder(cfg.folder, HDRI_EXT, "HDRI", cfg.files, cfg.exclude)

    def check(self, cfg: Any) -> None:
        for f in self.files(cfg):
            load_hdri(f, cfg.env_width)

    def open(self, cfg: Any) -> dict[str, Any]:
        return {"files": self.files(cfg), "maps": {}}

    def draw(self, state: dict[str, Any], cfg: Any, rng: np.random.Generator, camera: Any, size: tuple[int, int],
             rotation: float, scale: float) -> Background:
        f = state["files"][int(rng.integers(len(state["files"])))]
        if f not in state["maps"]:
            state["maps"][f] = load_hdri(f, cfg.env_width)
        return Background("hdri", state["maps"][f], rotation, scale, None, {"file": f.name, "rotation": rotation, "exposure": scale})

    def records(self, cfg: Any) -> set[str]:
        return set()
