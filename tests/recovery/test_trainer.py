"""recovery.trainer / recovery.train: an interrupted and resumed run is the uninterrupted run, step for
step (data order, augmentation, dropout, discriminator draws), also with a loader worker process."""

from __future__ import annotations

import os
import shutil
import signal

import pytest
import torch
from recovery_helpers import TRAIN_STEPS, one_thread, train_config, write_config

from recovery import trainer
from recovery.checkpoint import read_checkpoint
from recovery.cli import main
from recovery.tasks.hmr_task import HMRTask
from recovery.trainer import read_log

STOP_AFTER = 3


def _train_records(run):
    return [
        {k: v for k, v in r.items() if k != "time"}
        for r in read_log(run / "log.jsonl")
        if r["kind"] == "train"
    ]


@pytest.fixture(scope="module")
def resumed(tmp_path_factory, fake_root, train_cache):
    """The run of ``run_a`` with a loader worker process, interrupted by SIGINT during step
    STOP_AFTER, then resumed; returns its config file, the run folder, and a copy of the folder as
    it was when interrupted."""
    root = tmp_path_factory.mktemp("recovery_run_b")
    cfg = write_config(root / "config.yaml", train_config(fake_root, train_cache, data={"workers": 1}))
    out, stopped = root / "run", root / "stopped"
    mp = pytest.MonkeyPatch()
    mp.setattr(trainer, "plot_curves", lambda *a, **k: None)
    step = HMRTask.training_step

    def ctrl_c_in_step(self, batch, i):
        if i == STOP_AFTER - 1:
            os.kill(os.getpid(), signal.SIGINT)  # the trainer's handler: finish this step, checkpoint, stop
        return step(self, batch, i)

    try:
        with one_thread():
            mp.setattr(HMRTask, "training_step", ctrl_c_in_step)
            assert main(["train", str(cfg), "--out", str(out)]) == 130
            mp.setattr(HMRTask, "training_step", step)
            shutil.copytree(out, stopped)
            assert main(["train", str(cfg), "--out", str(out), "--resume"]) == 0
    finally:
        mp.undo()
    return cfg, out, stopped


def test_interrupt_writes_a_checkpoint_of_that_step(resumed):
    _, _, stopped = resumed
    ck = read_checkpoint(stopped / "last.pt")
    assert ck["step"] == STOP_AFTER and ck["consumed"] == STOP_AFTER * 4
    assert [r["step"] for r in _train_records(stopped)] == [1, 2, 3]


def test_resumed_run_equals_the_uninterrupted_run(run_a, resumed):
    _, out, _ = resumed
    a, b = _train_records(run_a), _train_records(out)
    assert [r["step"] for r in b] == list(range(1, TRAIN_STEPS + 1))  # each step logged once
    assert set(a[0]) >= {"kp2d", "kp3d", "pose", "orient", "bone", "shape", "adv", "disc", "total", "lr"}
    # Exactly equal: run_a loads in the main process, this run in a worker, from step 0 and from 3.
    assert b == a
    assert len({r["total"] for r in a}) == TRAIN_STEPS  # the losses change from step to step
    wa, wb = (read_checkpoint(r / "last.pt")["modules"] for r in (run_a, out))
    for name in ("model", "disc"):
        for k, v in wa[name].items():
            assert torch.equal(v, wb[name][k]), (name, k)
    val = [r for r in read_log(out / "log.jsonl") if r["kind"] == "val"]
    assert [r["step"] for r in val] == [TRAIN_STEPS]


def test_resume_without_the_random_state_differs(run_a, resumed, monkeypatch, tmp_path):
    """The comparison above can fail: continuing the same checkpoint without restoring torch's RNG
    (dropout masks) gives other losses from the first resumed step on."""
    cfg, _, stopped = resumed
    out = tmp_path / "run"
    shutil.copytree(stopped, out)
    monkeypatch.setattr(trainer, "plot_curves", lambda *a, **k: None)
    monkeypatch.setattr(torch, "set_rng_state", lambda state: None)
    assert main(["train", str(cfg), "--out", str(out), "--resume"]) == 0
    a, b = _train_records(run_a), _train_records(out)
    assert b[:STOP_AFTER] == a[:STOP_AFTER]
    for ra, rb in zip(a[STOP_AFTER:], b[STOP_AFTER:], strict=True):
        assert ra["kp3d"] != rb["kp3d"]


def test_resume_of_a_finished_run_does_nothing(run_a, resumed):
    cfg, out, _ = resumed
    before = (out / "last.pt").stat().st_mtime_ns
    assert main(["train", str(cfg), "--out", str(out), "--resume"]) == 0
    assert (out / "last.pt").stat().st_mtime_ns == before
    assert [r["step"] for r in _train_records(out)] == list(range(1, TRAIN_STEPS + 1))


def test_curves_are_drawn_from_the_log(run_a, tmp_path):
    from PIL import Image

    trainer.plot_curves(run_a / "log.jsonl", tmp_path / "curves.png")
    with Image.open(tmp_path / "curves.png") as im:
        assert im.size[0] > 500 and im.size[1] > 200
    assert not list(tmp_path.glob(".*"))  # no temporary file left
