"""Fixtures shared by the tests of blsm."""

from __future__ import annotations

import numpy as np
import pytest
import torch


@pytest.fixture(scope="session")
def selection(model):
    """The packaged landmark table (blsm/data/landmarks.yaml) as a landmark selection."""
    from blsm.learn.registration.landmark_fit import default_selection

    return default_selection(model)


@pytest.fixture
def one_thread():
    """One torch thread for the test (registration tests are timed against one core)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def coloured_body(model):
    """``coloured_body(seed, yaw)``: a posed body of the packaged model (random angles within 0.15 rad
    of rest, turned by ``yaw`` about the vertical) as a scan with random vertex colours and exact
    ground truth."""
    from blsm.learn.scans.format import Scan

    def make(seed: int, yaw: float) -> Scan:
        gen = torch.Generator().manual_seed(seed)
        angles = (torch.rand(1, model.num_dofs, generator=gen) - 0.5) * 0.3
        lo, hi = model.dof_limits[:, 0], model.dof_limits[:, 1]
        with torch.no_grad():
            out = model(angles=angles.clamp(lo, hi), global_orient=torch.tensor([[0.0, yaw, 0.0]]))
        v = out.vertices[0].double().numpy().astype(np.float32)
        colors = np.random.default_rng(0).integers(60, 200, size=(len(v), 3)).astype(np.uint8)
        return Scan(v, model.faces.numpy().astype(np.int32), [], np.zeros((0, 3), np.float32), {"id": "body"},
                    gt_points=v, gt_joints=out.joints[0].numpy(), colors=colors)

    return make
