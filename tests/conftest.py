from __future__ import annotations

from pathlib import Path

import pytest
import torch

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


@pytest.fixture(scope="session")
def model():
    import blsm

    return blsm.load()


@pytest.fixture(scope="session")
def model64(model):
    import blsm

    return blsm.load().double()


@pytest.fixture
def gen():
    return torch.Generator().manual_seed(0)


@pytest.fixture(scope="session")
def shared_mocap() -> Path:
    """The CMU clips of ../shared/mocap/cmu (CI always has them)."""
    path = SHARED / "mocap" / "cmu"
    if not (path / "002_01.bvh").is_file():
        pytest.skip(f"needs the shared CMU mocap clips at {path} (not present on this machine)")
    return path
