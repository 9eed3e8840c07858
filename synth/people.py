"""Who stands in an image or clip, and where: distinct subjects drawn from the pool
(:func:`draw_subject`, ``people.distinct`` of :class:`synth.config.PeopleConfig`), the run's warning
when the pool is too small (:func:`subject_pool_warning`), and the people's footprint discs placed
``people.gap`` apart on the ground (:func:`footprint`, :func:`place_people`). Used by single images
(:mod:`synth.sample`) and clips (:mod:`synth.sequence`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from synth.config import GeneratorConfig


def draw_subject(
    rng: np.random.Generator, pool: int, taken: Sequence[int], distinct: bool | None = None
) -> int:
    """The subject (an index into a pool of ``pool``) of the next person of an image or clip whose
    people so far have subjects ``taken``.

    Without replacement (``distinct`` None or True, :class:`synth.config.PeopleConfig`): a subject
    already in the image is drawn again, so the result is uniform over the others and an image whose
    people were distinct under the draw with replacement keeps its draws, and every later draw of its
    ``rng``. Once all ``pool`` subjects are in the image (more people than subjects) the pool starts
    afresh. ``distinct`` False: one draw with replacement, as before the key.
    """
    si = int(rng.integers(pool))
    if distinct is False:
        return si
    this_round = set(taken[len(taken) - len(taken) % pool :])  # the people since the pool last started afresh
    while si in this_round:
        si = int(rng.integers(pool))
    return si


def subject_pool_warning(cfg: GeneratorConfig, pool: int) -> str | None:
    """What a run of ``cfg`` with ``pool`` subjects says before it starts: a one-line warning when
    the pool is smaller than ``people.max`` (a subject repeats in an image), else None; a ValueError
    when ``people.distinct`` is true and the pool cannot give ``people.max`` different subjects."""
    p = cfg.people
    if pool >= p.max or p.distinct is False:
        return None
    src = "subjects.count" if cfg.subjects.source == "anny" else f"the usable scans in {cfg.subjects.folder}"
    subjects = f"{pool} subjects" if pool > 1 else "1 subject"
    what = f"people.max = {p.max} but there {'are' if pool > 1 else 'is'} {subjects} ({src})"
    if p.distinct:
        raise ValueError(f"people.distinct is true and {what}; add subjects or lower people.max")
    return (f"warning: {what}, so images with more people than that show a subject twice "
            "(people.distinct: true makes this an error)")


def footprint(outline: np.ndarray) -> tuple[np.ndarray, float]:
    """A person's footprint disc on the ground from its hull vertices ``outline`` (N, 3): the centre
    (2,) of their x-z bounding box and the radius around it that holds them all, metres."""
    xz = outline[:, [0, 2]]
    c = 0.5 * (xz.min(0) + xz.max(0))
    return c, float(np.linalg.norm(xz - c, axis=1).max())


def place_people(footprints: list[tuple[np.ndarray, float]], gap: float, rng: np.random.Generator) -> list[np.ndarray]:
    """Horizontal offsets so that the people's footprint discs (centre, radius) stay ``gap`` apart."""
    placed: list[tuple[np.ndarray, float]] = []
    offsets = []
    for centre, r in footprints:
        pos = np.zeros(2)
        if placed:
            for _ in range(200):
                ang = rng.uniform(0, 2 * math.pi)
                ref, rr = placed[int(rng.integers(len(placed)))]
                pos = ref + (rr + r + gap + rng.uniform(0.0, 0.8)) * np.array([math.cos(ang), math.sin(ang)])
                if all(np.linalg.norm(pos - q) >= rq + r + gap for q, rq in placed):
                    break
            else:  # pragma: no cover - 8 people always fit in 200 tries
                raise RuntimeError("could not place the people apart")
        placed.append((pos, r))
        offsets.append(np.array([pos[0] - centre[0], 0.0, pos[1] - centre[1]]))
    return offsets
