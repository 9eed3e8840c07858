"""Shared fixtures of the recovery tests: one small fake dataset (tests/synth/fakes.py, no Mitsuba),
its crop cache, and one tiny training run that the trainer, CLI, evaluate and predict tests reuse.

Everything runs on one CPU thread: the machine is small and shared, and a second OpenMP thread
waiting on a busy core makes these tiny convolutions many times slower.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from recovery_helpers import CONTEXT, CROP, one_thread, train_config, write_config

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "synth"))
from fakes import make_dataset  # noqa: E402


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    with one_thread():
        yield


@pytest.fixture(scope="session")
def fake_root(tmp_path_factory, model) -> Path:
    """A complete fake dataset: 6 images, 9 people (tests/synth/fakes.py)."""
    return make_dataset(tmp_path_factory.mktemp("recovery_fake") / "ds", model=model)


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory, fake_root) -> Path:
    """The fake dataset's crop cache for ``CROP`` px at ``CONTEXT``."""
    from recovery.datasets.cache import build_cache

    with one_thread():
        return build_cache(
            fake_root,
            tmp_path_factory.mktemp("recovery_cache") / "c",
            CROP,
            CONTEXT,
            workers=0,
            log=lambda *a: None,
        )


@pytest.fixture(scope="session")
def train_cache(tmp_path_factory) -> Path:
    """The cache root of the training runs (shared, so that only the first run builds it)."""
    return tmp_path_factory.mktemp("recovery_train_cache")


@pytest.fixture(scope="session")
def run_a(tmp_path_factory, fake_root, train_cache) -> Path:
    """The tiny run, uninterrupted (``last.pt``, ``best.pt``, ``log.jsonl``); curves are not drawn
    (matplotlib costs half a second per log line; ``plot_curves`` has its own test)."""
    from recovery import trainer
    from recovery.config import load_config
    from recovery.train import train

    root = tmp_path_factory.mktemp("recovery_run_a")
    cfg = load_config(write_config(root / "config.yaml", train_config(fake_root, train_cache)))
    out = root / "run"
    mp = pytest.MonkeyPatch()
    mp.setattr(trainer, "plot_curves", lambda *a, **k: None)
    try:
        with one_thread():
            assert train(cfg, out, log=lambda *a: None) == "done"
    finally:
        mp.undo()
    return out


@pytest.fixture(scope="session")
def mesh_cache(tmp_path_factory, model) -> Path:
    """An operator cache holding the packaged model's default mesh operators (built once, ~10 s)."""
    from recovery.config import MeshConfig
    from recovery.mesh.operators import mesh_operators

    root = tmp_path_factory.mktemp("mesh_ops")
    with one_thread():
        mesh_operators(None, root, MeshConfig().ops_settings(), log=lambda *a: None)
    return root
