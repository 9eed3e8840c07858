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
