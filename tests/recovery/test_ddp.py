"""recovery.distributed and ``recovery train`` under ``torchrun`` on the CPU (gloo).

The torchrun tests run in a new network namespace holding only the loopback interface
(``unshare -n``), so that no traffic leaves 127.0.0.1; they are skipped where no namespace can be
made.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from recovery_helpers import one_thread, train_config, write_config

from recovery import distributed as D
from recovery import trainer
from recovery.checkpoint import read_checkpoint
from recovery.config import RecoveryConfig, TrainConfig, load_config
from recovery.datasets.sampling import ResumableSampler, ShardedBatches
from recovery.models import losses as L
from recovery.tasks.hmr_task import HMRTask
from recovery.trainer import read_log

REPO = Path(__file__).resolve().parents[2]
PORT = 29511  # inside the private namespace: always free
STEPS, BATCH, STOP_AFTER = 20, 16, 10
LOSSES = ("kp2d", "kp3d", "pose", "orient", "bone", "shape", "adv", "disc", "total")
RUN_FILES = ["best.pt", "curves.png", "last.pt", "log.csv", "log.jsonl"]


# -- without processes


@pytest.mark.parametrize("world", [1, 2, 4])
@pytest.mark.parametrize("consumed", [0, 48])
def test_sharded_batches_together_are_the_single_process_batches(world, consumed):
    """The ranks' parts of every step, concatenated in rank order, are the single-process batch of
    that step, also from a resume position: the order does not depend on the process count."""
    n, b = 9, 16

    def sampler():
        return ResumableSampler(n, 0, consumed // n, consumed % n)

    one = iter(torch.utils.data.BatchSampler(sampler(), b, False))  # DataLoader(batch_size=b)'s batches
    parts = [iter(ShardedBatches(sampler(), b, r, world)) for r in range(world)]
    for step in range(5):
        assert [key for p in parts for key in next(p)] == next(one), step


def test_sharded_batches_need_a_divisible_batch():
    with pytest.raises(ValueError, match="divisible by the 3 processes"):
        ShardedBatches(ResumableSampler(9, 0), 16, 0, 3)


def test_environment():
    assert D.from_environment({}) == D.SINGLE and D.SINGLE.main and not D.SINGLE.distributed
    env = D.from_environment({"WORLD_SIZE": "4", "RANK": "3", "LOCAL_RANK": "1"})
    assert (env.rank, env.world_size, env.local_rank, env.main, env.distributed) == (3, 4, 1, False, True)
    with pytest.raises(ValueError, match="RANK 4"):
        D.from_environment({"WORLD_SIZE": "4", "RANK": "4"})
    with pytest.raises(ValueError, match="integers"):
        D.from_environment({"WORLD_SIZE": "two"})


def test_single_process_reductions_are_the_identity():
    x = torch.tensor([3.0, -1.0])
    assert D.all_sum(x) is x and D.rank_mean(x) is x and D.gather(x) is x
    assert torch.equal(D.share_normaliser(torch.tensor(0.0)), torch.tensor(1.0))


def test_keypoint_2d_shares_average_to_the_global_mean(gen):
    """Each half of a batch divided by the global visible count over 2 (the shares of
    :func:`recovery.distributed.share_normaliser`): their mean is the whole batch's loss, although
    the halves see different numbers of visible keypoints; the mean of the halves' own means is not."""
    pred = torch.rand(16, 44, 2, generator=gen) * 64
    visible = (torch.rand(16, 44, 1, generator=gen) > 0.3).float()
    target = torch.cat([torch.rand(16, 44, 2, generator=gen) * 64, visible], -1)
    target[:8, :30, 2] = 0.0  # the first half sees far fewer keypoints
    whole = L.keypoint_2d_loss(pred, target, 64)
    halves = (slice(0, 8), slice(8, 16))
    norm = target[..., 2].sum().clamp(min=1.0) / 2
    shares = [L.keypoint_2d_loss(pred[h], target[h], 64, norm) for h in halves]
    assert torch.allclose((shares[0] + shares[1]) / 2, whole, rtol=1e-6)
    local = [L.keypoint_2d_loss(pred[h], target[h], 64) for h in halves]
    assert not torch.allclose((local[0] + local[1]) / 2, whole, rtol=1e-3)


def test_sync_batchnorm_is_stored_only_when_changed():
    """A setting added after the first checkpoints: at its default it is not in the stored config,
    so those checkpoints still resume."""
    assert "sync_batchnorm" not in RecoveryConfig().to_dict()["train"]
    off = RecoveryConfig(train=TrainConfig(sync_batchnorm=False)).to_dict()["train"]
    assert off["sync_batchnorm"] is False


# -- torchrun in a private network namespace


def _namespace_problem() -> str | None:
    if sys.platform != "linux" or not shutil.which("unshare") or not shutil.which("ip"):
        return "needs Linux with unshare and ip (a private network namespace for torchrun)"
    try:
        res = subprocess.run(["unshare", "-n", "sh", "-c", "ip link set lo up"], capture_output=True,
                             timeout=30)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"cannot make a network namespace ({exc})"
    if res.returncode:
        return f"cannot make a network namespace (unshare -n: {res.stderr.decode().strip()[:120]})"
    return None


@pytest.fixture(scope="module")
def netns() -> None:
    problem = _namespace_problem()
    if problem:
        pytest.skip(problem)


def torchrun(args: list[str], timeout: float = 300) -> subprocess.CompletedProcess:
    """``torchrun --nproc-per-node 2 ARGS`` in a new network namespace with only loopback up."""
    run = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "1", "--nproc-per-node", "2",
           "--master-addr", "127.0.0.1", "--master-port", str(PORT), *args]
    drop = ("WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env.update(GLOO_SOCKET_IFNAME="lo", OMP_NUM_THREADS="1")
    script = f"ip link set lo up && exec {' '.join(run)}"
    return subprocess.run(["unshare", "-n", "sh", "-c", script], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=timeout)


def test_cpu_sync_batchnorm_equals_batchnorm_of_the_whole_batch(netns, tmp_path):
    """Two processes with half a batch each through CPUSyncBatchNorm: the outputs, input and
    parameter gradients and running statistics of a BatchNorm on the whole batch (float64;
    momentum 0.1 and the cumulative average)."""
    from syncbn_worker import inputs

    worker = Path(__file__).with_name("syncbn_worker.py")
    res = torchrun([str(worker), str(tmp_path / "out.pt")], timeout=120)
    assert res.returncode == 0, res.stderr[-3000:]
    got = torch.load(tmp_path / "out.pt")
    for name, x, bn, g in inputs():
        out = got[name]
        assert bool(out["synchronised"])
        xi = x.clone().requires_grad_()
        y = bn(xi)
        (y * g).sum().backward()
        want = {"y": y.detach(), "dx": xi.grad, "dw": bn.weight.grad, "db": bn.bias.grad,
                "mean": bn.running_mean, "var": bn.running_var, "tracked": bn.num_batches_tracked}
        for k, v in want.items():
            torch.testing.assert_close(out[k], v, rtol=1e-10, atol=1e-12, msg=f"{name} {k}")


@pytest.fixture(scope="module")
def ddp_config(tmp_path_factory, fake_root, train_cache) -> Path:
    """The acceptance run: 20 steps of 16, 64 px crops, dropout off, SyncBatchNorm on, Adam 5e-5."""
    root = tmp_path_factory.mktemp("recovery_ddp")
    cfg = train_config(
        fake_root, train_cache, model={"dropout": 0.0}, data={"crop": 64},
        optim={"lr": 5e-5, "warmup_steps": 2},
        train={"steps": STEPS, "batch_size": BATCH, "val_every": STEPS, "checkpoint_every": 100, "threads": 1,
               "sync_batchnorm": True})
    return write_config(root / "config.yaml", cfg)


def _train_here(cfg_path: Path, out: Path, stop_after: int | None = None) -> str:
    """``recovery.train.train`` in this process (one thread, no curves); with ``stop_after``, a
    Ctrl-C during that step."""
    from recovery.train import train

    mp = pytest.MonkeyPatch()
    mp.setattr(trainer, "plot_curves", lambda *a, **k: None)
    if stop_after is not None:
        step = HMRTask.training_step

        def ctrl_c_in_step(self, batch, i):
            if i == stop_after - 1:
                os.kill(os.getpid(), signal.SIGINT)  # the trainer's handler: finish the step, checkpoint
            return step(self, batch, i)

        mp.setattr(HMRTask, "training_step", ctrl_c_in_step)
    try:
        with one_thread():
            return train(load_config(cfg_path), out, log=lambda *a: None)
    finally:
        mp.undo()


def _train_torchrun(cfg_path: Path, out: Path, *extra: str) -> None:
    """``torchrun --nproc-per-node 2 -m recovery.cli train CONFIG --out OUT``; its console output
    goes to ``OUT.log``."""
    res = torchrun(["-m", "recovery.cli", "train", str(cfg_path), "--out", str(out), *extra])
    out.with_suffix(".log").write_text(res.stdout + res.stderr)
    assert res.returncode == 0, res.stderr[-3000:]


@pytest.fixture(scope="module")
def ddp_runs(netns, ddp_config) -> dict[str, Path]:
    """The single-process run and the same config on two processes; returns the run folders."""
    one, two = ddp_config.parent / "one", ddp_config.parent / "two"
    assert _train_here(ddp_config, one) == "done"
    _train_torchrun(ddp_config, two)
    return {"one": one, "two": two}


def _train_records(run: Path) -> list[dict]:
    return [r for r in read_log(run / "log.jsonl") if r["kind"] == "train"]


def _relative(a: list[dict], b: list[dict]) -> list[dict[str, float]]:
    """Per step, per loss term: |a - b| / |a|."""
    return [{k: abs(ra[k] - rb[k]) / abs(ra[k]) for k in LOSSES} for ra, rb in zip(a, b, strict=True)]


def test_two_processes_give_the_single_process_losses(ddp_runs):
    """Acceptance: ``torchrun --nproc-per-node 2`` (gloo, one thread each), 20 steps at global batch
    16 (8 per process), dropout off, SyncBatchNorm on, against one process at batch 16: every logged
    loss term within 1e-3 (relative) at every step, and within 1e-5 at the first step (its losses
    come before any update; measured about 1e-7).

    Seed 0 (``train.seed``) for the initialisation, the data order, the augmentation and the
    real-pose draws. Data order: the fake dataset's 9 people in the permutation
    ``numpy.random.default_rng([0, epoch])`` per epoch (:class:`recovery.datasets.sampling.ResumableSampler`),
    cut into global batches of 16 consecutive keys (a batch runs on into the next epoch); rank r
    takes keys 8 r .. 8 r + 7 of each batch, so both runs see the same 16 crops at every step,
    each augmented from ``(0, epoch, item)``.

    Adam at 5e-5 (SPIN's rate): at the default 3e-4 two single-process runs that differ only in
    their thread count already drift apart by up to 4e-3 in 20 steps (float32 rounding that Adam
    amplifies), so the comparison would measure that noise, not the split.
    """
    a, b = _train_records(ddp_runs["one"]), _train_records(ddp_runs["two"])
    assert [r["step"] for r in b] == list(range(1, STEPS + 1))  # rank 0 alone logged, once per step
    rel = _relative(a, b)
    worst = {k: max(r[k] for r in rel) for k in LOSSES}
    summary = " ".join(f"{k} {v:.1e}" for k, v in worst.items())
    print(f"\nmax relative difference over {STEPS} steps: {summary}; step 1: {max(rel[0].values()):.1e}")
    assert max(rel[0].values()) < 1e-5, rel[0]
    assert max(worst.values()) < 1e-3, worst
    assert len({r["total"] for r in a}) == STEPS and [r["lr"] for r in a] == [r["lr"] for r in b]


def test_rank_0_writes_one_run_folder(ddp_runs):
    """One log, one validation, ``last.pt`` and ``best.pt`` from rank 0; the checkpoint records the
    global position and every rank's RNG, and loads into the single-process network."""
    import blsm
    from recovery.models.registry import build_hmr

    two = ddp_runs["two"]
    assert sorted(p.name for p in two.iterdir()) == RUN_FILES
    assert [r["step"] for r in read_log(two / "log.jsonl") if r["kind"] == "val"] == [STEPS]
    assert len((two / "log.csv").read_text().splitlines()) == STEPS + 1
    console = two.with_suffix(".log").read_text()  # rank 0 alone prints
    assert console.count("[val] step 20") == 1 and console.count("20 steps of 16 (2 processes of 8)") == 1
    ck, ref = read_checkpoint(two / "last.pt"), read_checkpoint(ddp_runs["one"] / "last.pt")
    assert ck["step"] == STEPS and ck["consumed"] == STEPS * BATCH and ck["world_size"] == 2
    assert len(ck["rank_rng"]) == 2 and torch.equal(ck["rank_rng"][0][0], ck["torch_rng"])
    assert not torch.equal(ck["rank_rng"][0][0], ck["rank_rng"][1][0])  # each rank its own dropout masks
    model = build_hmr(load_config(two.parent / "config.yaml"), blsm.load(), pretrained=False)
    model.load_state_dict(ck["modules"]["model"])  # strict: the SyncBatchNorm layers saved as BatchNorm
    assert ck["modules"]["model"].keys() == ref["modules"]["model"].keys()


@pytest.mark.slow
def test_resume_on_another_number_of_processes(ddp_runs, ddp_config):
    """The single-process run interrupted at step 10 and resumed on two processes: steps 11-20 are
    the single-process run's (the global batch and order do not depend on the process count)."""
    stopped, resumed = ddp_config.parent / "stopped", ddp_config.parent / "resumed"
    assert _train_here(ddp_config, stopped, stop_after=STOP_AFTER) == "interrupted"
    shutil.copytree(stopped, resumed)
    _train_torchrun(ddp_config, resumed, "--resume")
    one, after = _train_records(ddp_runs["one"]), _train_records(resumed)
    assert [r["step"] for r in after] == list(range(1, STEPS + 1))
    assert after[:STOP_AFTER] == _train_records(stopped)
    rel = _relative(one[STOP_AFTER:], after[STOP_AFTER:])
    assert max(rel[0].values()) < 1e-5, rel[0]
    assert max(max(r.values()) for r in rel) < 1e-3
    ck = read_checkpoint(resumed / "last.pt")
    assert ck["consumed"] == STEPS * BATCH and ck["world_size"] == 2 and len(ck["rank_rng"]) == 2
