"""``background.kind: images``: a folder of backplates (``.jpg``, ``.jpeg``, ``.png``, ``.exr``,
``.hdr``, ``.tif``); each image draws one, crops it to the image's aspect at a random place (on the
camera's horizon where the folder's ``plates.json`` gives the plate's) and resizes it (OpenImageIO).
People are lit by the procedural sky (hidden) and composited over the plate with the render's
anti-aliased coverage."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from synth.backgrounds.base import Background
from synth.backgrounds.files import IMAGE_EXT, list_folder, read_image, resize_image
from synth.backgrounds.sky import procedural_sky


def crop_backplate(image: np.ndarray, width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    """A random crop of ``image`` at the target aspect (at least 60 % of the shorter side), resized."""
    h, w = image.shape[:2]
    aspect = width / height
    ch = int(min(h, w / aspect) * rng.uniform(0.6, 1.0))
    cw = max(1, int(round(ch * aspect)))
    ch = max(1, ch)
    y0 = int(rng.integers(0, h - ch + 1))
    x0 = int(rng.integers(0, w - cw + 1))
    return resize_image(image[y0 : y0 + ch, x0 : x0 + cw], width, height)


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
    return resize_image(image[y0:y0 + ch, x0:x0 + cw], width, height)


class Plates:
    """The kind ``images`` (:class:`synth.backgrounds.base.BackgroundKind`)."""

    name, needs_folder, follows_cameras = "images", True, False

    def files(self, cfg: Any) -> list[Path]:
        return list_folder(cfg.folder, IMAGE_EXT, "background image", cfg.files, cfg.exclude)

    def check(self, cfg: Any) -> None:
        for f in self.files(cfg):
            read_image(f)
        if cfg.align_horizon:
            read_horizons(cfg.folder)  # a bad plates.json is an error before any work

    def open(self, cfg: Any) -> dict[str, Any]:
        return {"files": self.files(cfg), "images": {}, "horizons": read_horizons(cfg.folder) if cfg.align_horizon else {}}

    def draw(self, state: dict[str, Any], cfg: Any, rng: np.random.Generator, camera: Any, size: tuple[int, int],
             rotation: float, scale: float) -> Background:
        env, info = procedural_sky(cfg.env_width, rng)
        width, height = size
        f = state["files"][int(rng.integers(len(state["files"])))]
        if f not in state["images"]:
            state["images"][f] = read_image(f)
        extra: dict[str, Any] = {}
        plate = None
        if state["horizons"]:  # a described bank: the plate's horizon on the camera's (plates.json)
            hz = state["horizons"].get(f.name)
            row = horizon_row(camera.K, camera.R) if hz is not None else None
            if row is not None:
                plate = crop_backplate_at_horizon(state["images"][f], hz, width, height, row, rng)
            extra = {"horizon_row": row if plate is not None else None}
        if plate is None:
            plate = crop_backplate(state["images"][f], width, height, rng)
        return Background("images", env, rotation, scale, plate,
                          {"file": f.name, "rotation": rotation, "exposure": scale, **info, **extra})

    def records(self, cfg: Any) -> set[str]:
        return {"align_horizon"} if read_horizons(cfg.folder) else set()
