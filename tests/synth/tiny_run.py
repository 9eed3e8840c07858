"""The tiny dataset that the generator's tests share (``tiny`` in ``tests/synth/conftest.py``): 6
images of 96 px in 2 shards, 2 Anny people of 128 px textures, 1-2 a sample."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

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
