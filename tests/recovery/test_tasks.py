"""recovery.tasks: every task a config may name is registered, and found by name."""

from __future__ import annotations

import pytest

from recovery import config
from recovery.predictor import TASKS as PREDICTS
from recovery.tasks import TASKS, get_task


def test_every_config_task_is_registered_under_its_name():
    assert tuple(TASKS) == config.TASKS
    for name, spec in TASKS.items():
        assert spec.name == name
        assert callable(spec.setup) and callable(spec.batches) and callable(spec.describe)
    assert get_task("autoencoder").best_metric == "vertex_mm"
    assert get_task("hmr_blsm").best_metric == get_task("mesh").best_metric == "pa_mpjpe_mm"
    assert [n for n, s in TASKS.items() if s.distributed] == ["hmr_blsm"]
    assert PREDICTS == ("hmr_blsm", "mesh")  # the autoencoder has no inference network


def test_unknown_task_is_a_one_line_error():
    with pytest.raises(ValueError, match="unknown task 'pose'; known: hmr_blsm, mesh, autoencoder"):
        get_task("pose")
