"""Backgrounds and lighting, one module per kind of ``background.kind`` and one line of :data:`KINDS`
each (:class:`synth.backgrounds.base.BackgroundKind`: check, open, draw, records):

- ``hdri`` (:mod:`.hdri`): a folder of latitude-longitude environment maps (``.exr``, ``.hdr``), read and resized
  with OpenImageIO. The environment is visible behind the people and lights them; each image draws
  a rotation about +Y and an exposure. Maps are normalised to a mean luminance of ``MEAN_LUMINANCE`` first, so one
  exposure range suits every file.
- ``images`` (:mod:`.plates`): a folder of backplates (``.jpg``, ``.jpeg``, ``.png``, ``.exr``, ``.hdr``, ``.tif``);
  each image draws one, crops it to the image's aspect at a random place and resizes it (OpenImageIO).
  People are lit by the procedural sky (hidden) and composited over the plate with the render's
  anti-aliased coverage.
- ``default`` (:mod:`.sky`): the embedded procedural sky (no files): a sky gradient, a sun and a ground plane
  colour, drawn per image.

Bad input (a missing or empty folder, an unreadable file) is a ValueError naming the path; a kind's
``check`` opens and decodes every file of a run before any work starts (:mod:`.files`).
"""

from __future__ import annotations

from synth.backgrounds.base import Background, BackgroundKind
from synth.backgrounds.hdri import Hdri
from synth.backgrounds.plates import Plates
from synth.backgrounds.sky import Sky

__all__ = ["KINDS", "Background", "BackgroundKind", "background_kind"]

KINDS: dict[str, BackgroundKind] = {}
KINDS["default"] = Sky()
KINDS["hdri"] = Hdri()
KINDS["images"] = Plates()


def background_kind(name: str) -> BackgroundKind:
    """The kind of ``background.kind``; a ValueError naming the known ones."""
    if name not in KINDS:
        raise ValueError(f"background.kind must be one of {', '.join(KINDS)}, got {name!r}")
    return KINDS[name]