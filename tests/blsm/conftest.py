"""Fixtures shared by the tests of blsm."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(scope="session")
def selection(model):
    """The packaged landmark table (blsm/data/landmarks.yaml) as a landmark selection."""
    from blsm.learn.landmark_fit import default_selection

    return default_selection(model)


@pytest.fixture
def one_thread():
    """One torch thread for the test (registration tests are timed against one core)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
