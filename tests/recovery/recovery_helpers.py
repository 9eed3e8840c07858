"""Constants and helpers of the recovery tests (imported by conftest.py and the test modules)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
import yaml

CROP = 32  # network input of every test network, pixels
CONTEXT = 1.5  # recovery.config.DataConfig's default

# The training run of the trainer / CLI tests: the default EfficientNet-Lite0 without ImageNet
# weights (a quarter of ResNet-18's parameters, so a checkpoint is about 40 MB instead of 150 MB),
# a narrow regressor with dropout, the discriminator and augmentation on, six steps of four.
TRAIN_STEPS = 6


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """One torch thread, and numpy's error handling restored afterwards (``recovery.train.train``
    sets ``np.seterr(all="ignore")`` for the whole process)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with np.errstate():
            yield
    finally:
        torch.set_num_threads(n)


def train_config(fake_root: Path, cache: Path, **changes: dict) -> dict:
    """The tiny run's configuration as a dict; ``changes`` updates sections (``optim={"lr": 1e-3}``)."""
    cfg = {
        "model": {"backbone": "efficientnet_lite0", "pretrained": False, "hidden": 64, "dropout": 0.5},
        "data": {
            "train": [str(fake_root)],
            "val": str(fake_root),
            "crop": CROP,
            "cache": str(cache),
            "workers": 0,
        },
        "discriminator": {"prior_samples": 256},
        "optim": {"warmup_steps": 2},
        "train": {
            "steps": TRAIN_STEPS,
            "batch_size": 4,
            "val_every": 100,
            "checkpoint_every": 100,
            "log_every": 1,
            "device": "cpu",
        },
    }
    for section, values in changes.items():
        cfg[section] = {**cfg[section], **values}
    return cfg


def write_config(path: Path, cfg: dict) -> Path:
    path.write_text(yaml.safe_dump(cfg))
    return path


def sphere(subdivisions: int = 2, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A closed, outward-wound icosphere with radially jittered vertices (no distance ties)."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    rng = np.random.default_rng(seed)
    v = m.vertices * (1 + 0.05 * rng.random((len(m.vertices), 1)))
    return v, np.asarray(m.faces)
