"""The tiny dataset that the generator's tests share (``tiny`` in ``tests/synth/conftest.py``): 6
images of 96 px in 2 shards, 2 Anny people of 128 px textures, 1-2 a sample."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

from synth.camera import CameraConfig
from synth.config import (
    BackgroundConfig,
    GeneratorConfig,
    OutputConfig,
    PeopleConfig,
    RenderConfig,
    SubjectsConfig,
)

TINY = GeneratorConfig(
    seed=7,
    num=6,
    subjects=SubjectsConfig(count=2, texture_size=128),
    people=PeopleConfig(min=1, max=2),
    camera=CameraConfig(width=96, height=96, rare_rate=0.2, truncation_rate=0.3),
    background=BackgroundConfig(env_width=128),
    render=RenderConfig(spp=4),
    output=OutputConfig(shard_size=3),
)
TINY_YAML = """seed: 7
num: 6
subjects: {count: 2, texture_size: 128}
people: {min: 1, max: 2}
camera: {width: 96, height: 96, rare_rate: 0.2, truncation_rate: 0.3}
background: {env_width: 128}
render: {spp: 4}
output: {shard_size: 3}
"""


def copy_subjects(src: Path, dst: Path) -> None:
    """The subjects of dataset ``src`` into ``dst`` (a run into ``dst`` then reuses them)."""
    shutil.copytree(src / "subjects", dst / "subjects")


def shard_digests(path: Path) -> dict[str, str]:
    """Shard name -> SHA-256 of the dataset at ``path``, from its manifest."""
    return {k: v["sha256"] for k, v in json.loads((path / "manifest.json").read_text())["shards"].items()}


class Drawn(Exception):
    """Raised by a :func:`drawing_maker`'s renderer with the subjects (``si``) of the people it got."""


def drawing_maker(cfg: GeneratorConfig, tiny: Path, pool: int) -> Any:
    """A worker's :class:`synth.sample.SampleMaker` of ``cfg`` that draws people from a pool of
    ``pool`` subjects and stops before rendering: the ``tiny`` dataset's two subjects repeated
    (subject ``i`` is posed as subject ``i % 2``, keeping ``si = i``), and a renderer that raises
    :class:`Drawn`. What a sample or sequence draws, without building ``pool`` subjects."""
    from synth.sample import SampleMaker

    m = SampleMaker(cfg, tiny, "scalar_rgb", threads=1)
    m.subjects = [m.subjects[i % len(m.subjects)] for i in range(pool)]
    pose = m.pose

    def pose_as(si: int, *args: Any) -> Any:
        p = pose(si % 2, *args)
        p.si = si
        return p

    def stop(scene: Any, *args: Any, **kwargs: Any) -> Any:
        raise Drawn([p.si for p in scene.people])

    m.pose, m.render_frame = pose_as, stop
    return m


def drawn(make: Callable[[int, Any], Any], index: int, rng: Any) -> list[int]:
    """The subjects that ``make(index, rng)`` (of a :func:`drawing_maker`) drew, in order."""
    try:
        make(index, rng)
    except Drawn as d:
        return d.args[0]
    raise AssertionError(f"{index}: rendered, or drew no one")
