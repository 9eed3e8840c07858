"""A generic training loop, apart from any model's step (STYLE rule 10; the habits of HMR 2.0 /
Lightning, without the framework).

The loop owns: the device, the seeded and resumable data order, checkpoints (written atomically
every ``checkpoint_every`` steps, on SIGINT and at the end), validation every ``val_every`` steps,
a progress line with the rate, the ETA and the current losses, ``log.jsonl`` / ``log.csv`` and
``curves.png`` (training losses and the validation error) updated while it trains. A :class:`Task`
owns the networks, optimisers and schedulers, one training step (forward, losses, backward,
updates; a non-finite loss raises) and the validation metrics.

``last.pt`` holds everything needed to continue exactly: every module's, optimiser's and
scheduler's state, the task's own random state, torch's RNG, the step and the position in the
data order; ``resume`` continues with the same batches, augmentation and dropout masks as an
uninterrupted run (on CPU; GPU kernels are not bit-reproducible).

Under ``torchrun`` (:mod:`recovery.distributed`) every process runs this loop on its part of each
global batch; rank 0 alone prints, validates, logs and writes checkpoints while the others wait for
it, a Ctrl-C on any process stops them all after the same step, and ``last.pt`` also holds every
rank's torch RNG (each rank draws its own dropout masks).
"""

from __future__ import annotations

import csv
import json
import math
import os
import signal
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Protocol

import torch

from recovery import distributed as D
from recovery.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, read_checkpoint, save_atomic


class Task(Protocol):
    """What a model brings to :class:`Trainer`."""

    name: str

    def modules(self) -> dict[str, torch.nn.Module]: ...

    def optimizers(self) -> dict[str, torch.optim.Optimizer]: ...

    def schedulers(self) -> dict[str, Any]: ...

    def to(self, device: torch.device) -> None: ...

    def distribute(self, env: D.DistEnv, device: torch.device) -> None:
        """Wrap the networks for several processes (called after ``to`` when ``env.distributed``)."""
        ...

    def training_step(self, batch: dict[str, torch.Tensor], step: int) -> dict[str, float]: ...

    def validate(self, loader: Any) -> dict[str, float]: ...

    def extra_state(self) -> dict[str, Any]: ...

    def load_extra_state(self, state: dict[str, Any]) -> None: ...

    def checkpoint_meta(self) -> dict[str, Any]: ...


class Progress:
    """One status line: step, rate, ETA, losses (redrawn on a terminal, every 30 s otherwise; not
    written when ``stream`` is None: the ranks other than 0)."""

    def __init__(self, total: int, start: int, stream: Any = sys.stderr) -> None:
        self.total, self.start, self.stream = total, start, stream
        self.t0 = self.last = time.perf_counter()
        self.tty = hasattr(stream, "isatty") and stream.isatty()

    def update(self, step: int, images: int, losses: dict[str, float], force: bool = False) -> str:
        now = time.perf_counter()
        done = step - self.start
        rate = done / max(now - self.t0, 1e-9)
        eta = (self.total - step) / rate if rate > 0 else float("inf")
        ips = images / max(now - self.t0, 1e-9)
        eta_s = "?" if not math.isfinite(eta) else time.strftime("%H:%M:%S", time.gmtime(eta))
        body = " ".join(f"{k} {v:.4g}" for k, v in losses.items())
        line = f"[train] step {step}/{self.total} ({100 * step / self.total:.0f} %) {ips:.1f} img/s ETA {eta_s} | {body}"
        if self.stream is None:
            return line
        if self.tty:
            self.stream.write("\r" + line[:200].ljust(120))
            self.stream.flush()
        elif force or now - self.last > 30:
            self.stream.write(line + "\n")
            self.stream.flush()
            self.last = now
        return line


class Trainer:
    """Runs a :class:`Task` for ``steps`` steps (module docstring).

    Args:
        task: the model's step and metrics.
        out: run folder (``last.pt``, ``best.pt``, ``log.jsonl``, ``log.csv``, ``curves.png``).
        make_loader: ``consumed -> iterator of batches`` continuing the data order after
            ``consumed`` items (the order is endless: epoch ``consumed // epoch_size``); with
            several processes ``consumed`` counts global batches' items and each process gets its
            part of every global batch.
        val_loader: validation batches (re-iterated each time), or None.
        steps, batch_size, val_every, checkpoint_every, log_every: the schedule.
        config: the run's configuration (stored in checkpoints; a resume must match it).
        best_metric: the validation metric whose minimum writes ``best.pt``.
        epoch_size: items per epoch (for the logged epoch).
        env: this process among torchrun's (:data:`recovery.distributed.SINGLE` for a plain run).
        seed: the run's seed (rank ``r > 0``'s own random stream is derived from it).
    """

    def __init__(self, task: Task, out: str | Path, make_loader: Callable[[int, int], Iterator[dict[str, Any]]],
                 val_loader: Any, *, steps: int, batch_size: int, val_every: int, checkpoint_every: int,
                 log_every: int, config: dict[str, Any], epoch_size: int, device: torch.device,
                 best_metric: str = "pa_mpjpe_mm", env: D.DistEnv = D.SINGLE, seed: int = 0) -> None:
        self.task, self.out, self.make_loader, self.val_loader = task, Path(out), make_loader, val_loader
        self.steps, self.batch_size = steps, batch_size
        self.val_every, self.checkpoint_every, self.log_every = val_every, checkpoint_every, log_every
        self.config, self.epoch_size, self.device, self.best_metric = config, epoch_size, device, best_metric
        self.env, self.seed = env, seed
        self.step, self.consumed = 0, 0
        self.best = float("inf")
        self._stop = False
        self._logs_since_plot = 0
        self._rank_rng: list[Any] | None = None  # every rank's RNG, restored by _run (several processes)

    # -- checkpoints
    def state(self, rank_rng: list[Any] | None = None) -> dict[str, Any]:
        """The checkpoint; ``rank_rng``: every rank's ``(torch RNG, CUDA RNG)`` (several processes)."""
        t = self.task
        return {
            "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "task": t.name,
            "config": self.config, **t.checkpoint_meta(),
            "step": self.step, "consumed": self.consumed, "best": self.best,
            "modules": {k: m.state_dict() for k, m in t.modules().items()},
            "optimizers": {k: o.state_dict() for k, o in t.optimizers().items()},
            "schedulers": {k: s.state_dict() for k, s in t.schedulers().items()},
            "task_state": t.extra_state(),
            "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
            "world_size": self.env.world_size,
            **({"rank_rng": rank_rng} if rank_rng is not None else {}),
            "saved": time.strftime("%Y-%m-%dT%H:%M:%S"),
        }

    def save(self, name: str = "last.pt") -> Path:
        """Write ``name`` (rank 0; with several processes every rank calls this and waits for it)."""
        path = self.out / name
        rank_rng = self._gather_rng() if self.env.distributed else None
        if self.env.main:
            save_atomic(self.state(rank_rng), path)
        D.barrier()
        return path

    def _gather_rng(self) -> list[Any]:
        import torch.distributed as dist

        mine = (torch.get_rng_state(), torch.cuda.get_rng_state() if self.device.type == "cuda" else None)
        every: list[Any] = [None] * self.env.world_size
        dist.all_gather_object(every, mine)
        return every

    def resume(self, path: str | Path) -> None:
        """Restore everything from ``path``; a checkpoint of another task or config is a ValueError."""
        ck = read_checkpoint(path)
        if ck.get("task") != self.task.name:
            raise ValueError(f"{path}: a checkpoint of task {ck.get('task')!r}, not {self.task.name!r}")
        if json.dumps(ck["config"], sort_keys=True) != json.dumps(self.config, sort_keys=True):
            diff = _first_difference(ck["config"], self.config)
            raise ValueError(f"{path}: made with another config ({diff}); start a new run folder")
        for key, want in self.task.checkpoint_meta().items():
            if ck.get(key) != want:
                raise ValueError(f"{path}: made for another {key} ({ck.get(key)!r}, now {want!r})")
        t = self.task
        for k, m in t.modules().items():
            m.load_state_dict(ck["modules"][k])
        for k, o in t.optimizers().items():
            o.load_state_dict(ck["optimizers"][k])
        for k, s in t.schedulers().items():
            s.load_state_dict(ck["schedulers"][k])
        t.load_extra_state(ck["task_state"])
        torch.set_rng_state(ck["torch_rng"])
        if ck.get("cuda_rng") and torch.cuda.is_available() and not self.env.distributed:
            torch.cuda.set_rng_state_all(ck["cuda_rng"])
        self.step, self.consumed, self.best = ck["step"], ck["consumed"], ck["best"]
        self._rank_rng = ck.get("rank_rng")
        if self.env.main:
            _truncate_logs(self.out, self.step)
        D.barrier()  # the logs are cut before any rank trains on

    # -- the loop
    def run(self) -> str:
        """Train to ``steps``; returns "done" or "interrupted" (after writing ``last.pt``)."""
        if self.env.main:
            self.out.mkdir(parents=True, exist_ok=True)
        previous = signal.signal(signal.SIGINT, self._on_sigint)
        try:
            return self._run()
        finally:
            signal.signal(signal.SIGINT, previous)

    def _on_sigint(self, signum: int, frame: Any) -> None:
        if self._stop:  # a second Ctrl-C: stop now (the last checkpoint stays)
            raise KeyboardInterrupt
        self._stop = True
        if self.env.main:
            sys.stderr.write("\n[train] interrupt: writing the checkpoint after this step "
                             "(Ctrl-C again to abort)\n")

    def _stopping(self) -> bool:
        """Whether any process was interrupted (all stop after the same step). ``_stop`` is only
        read here: the handler may set it while the all-reduce runs."""
        if not self.env.distributed:
            return self._stop
        return bool(D.all_sum(torch.tensor([float(self._stop)], device=self.device)).item() > 0)

    def _seed_ranks(self) -> None:
        """Each rank's own random stream (dropout masks): rank 0 keeps the single-process stream,
        rank r > 0 one derived from the seed; a resume restores each rank's saved state, and ranks a
        checkpoint of fewer processes lacks start a stream derived from the seed, rank and step."""
        r = self.env.rank
        saved = self._rank_rng
        if saved is not None and r < len(saved):
            cpu, cuda = saved[r]
            torch.set_rng_state(cpu)
            if cuda is not None and self.device.type == "cuda":
                torch.cuda.set_rng_state(cuda)
        elif r > 0:
            torch.manual_seed(D.rank_seed(self.seed, r, self.step))

    def _run(self) -> str:
        self.task.to(self.device)
        if self.env.distributed:
            self.task.distribute(self.env, self.device)
            self._seed_ranks()
        progress = Progress(self.steps, self.step, sys.stderr if self.env.main else None)
        # Making a DataLoader iterator draws from torch's RNG; a resumed run makes one more than an
        # uninterrupted one, so the draw must not shift the dropout masks that follow.
        rng = torch.get_rng_state()
        loader = self.make_loader(self.consumed)
        torch.set_rng_state(rng)
        sums: dict[str, float] = {}
        count, images = 0, 0
        while self.step < self.steps:
            batch = next(loader)
            keys = batch["key"]
            n = int(keys.shape[0]) * self.env.world_size  # the global batch
            self.consumed += n
            losses = self.task.training_step(batch, self.step)  # global values of the losses
            self.step += 1
            images += n
            for k, v in losses.items():
                sums[k] = sums.get(k, 0.0) + v
            count += 1
            if self.step % self.log_every == 0 or self.step == self.steps:
                mean = {k: v / count for k, v in sums.items()}
                progress.update(self.step, images, mean)
                if self.env.main:
                    self._log({"kind": "train", "step": self.step, "epoch": self.consumed / self.epoch_size,
                               "time": time.time(), **mean})
                sums, count = {}, 0
            if self.val_loader is not None and (self.step % self.val_every == 0 or self.step == self.steps):
                self.validate()
            stop = self._stopping()
            if self.step % self.checkpoint_every == 0 or self.step == self.steps or stop:
                self.save()
            if stop:
                progress.update(self.step, images, {}, force=True)
                return "interrupted"
        progress.update(self.step, images, {}, force=True)
        return "done"

    def validate(self) -> dict[str, float]:
        """Validate on rank 0 (the others wait); writes ``best.pt`` at a new minimum. Returns the
        metrics (empty on the other ranks)."""
        metrics: dict[str, float] = {}
        improved = False
        if self.env.main:
            t0 = time.perf_counter()
            metrics = self.task.validate(self.val_loader)
            rec = {"kind": "val", "step": self.step, "time": time.time(), "seconds": time.perf_counter() - t0,
                   **metrics}
            self._log(rec)
            sys.stderr.write(("\n" if sys.stderr.isatty() else "") + "[val] step {}: {}\n".format(
                self.step, " ".join(f"{k} {v:.4g}" for k, v in metrics.items())))
            value = metrics.get(self.best_metric, float("inf"))
            improved = value < self.best
        if self.env.distributed:  # rank 0's verdict (the others wait here during validation)
            improved = bool(D.all_sum(torch.tensor([float(improved)], device=self.device)).item() > 0)
        if improved:
            if self.env.main:
                self.best = metrics[self.best_metric]
            self.save("best.pt")
        return metrics

    def _log(self, rec: dict[str, Any]) -> None:
        with open(self.out / "log.jsonl", "a") as fh:
            fh.write(json.dumps(rec) + "\n")
        if rec["kind"] == "train":
            _append_csv(self.out / "log.csv", rec)
            self._logs_since_plot = getattr(self, "_logs_since_plot", 0) + 1
        # Drawing takes about 0.5 s: after every validation, every 10th log line and the last step.
        if rec["kind"] == "val" or self._logs_since_plot >= 10 or rec["step"] == self.steps:
            plot_curves(self.out / "log.jsonl", self.out / "curves.png", self.best_metric)
            self._logs_since_plot = 0


def _first_difference(a: Any, b: Any, key: str = "") -> str:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if json.dumps(a.get(k), sort_keys=True) != json.dumps(b.get(k), sort_keys=True):
                return _first_difference(a.get(k), b.get(k), f"{key}.{k}" if key else k)
    return f"{key}: {a!r} vs {b!r}"


def _append_csv(path: Path, rec: dict[str, Any]) -> None:
    fields = [k for k in rec if k != "kind"]
    new = not path.is_file()
    if not new:
        with open(path) as fh:
            header = fh.readline().strip().split(",")
        if header != fields:  # the losses changed (a new run in an old folder): start over
            new = True
    with open(path, "w" if new else "a", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=fields)
        if new:
            w.writeheader()
        w.writerow({k: rec[k] for k in fields})


def _truncate_logs(out: Path, step: int) -> None:
    """Drop log records written after ``step`` (an interrupted run logged past its checkpoint)."""
    path = out / "log.jsonl"
    if path.is_file():
        keep = [ln for ln in path.read_text().splitlines() if ln.strip() and json.loads(ln)["step"] <= step]
        path.write_text("".join(ln + "\n" for ln in keep))
    csv_path = out / "log.csv"
    if csv_path.is_file():
        lines = csv_path.read_text().splitlines()
        if lines:
            idx = lines[0].split(",").index("step")
            kept = [lines[0]] + [ln for ln in lines[1:] if int(ln.split(",")[idx]) <= step]
            csv_path.write_text("\n".join(kept) + "\n")


def read_log(path: str | Path) -> list[dict[str, Any]]:
    path = Path(path)
    if not path.is_file():
        return []
    return [json.loads(ln) for ln in path.read_text().splitlines() if ln.strip()]


def plot_curves(log: str | Path, png: str | Path, val_metric: str = "pa_mpjpe_mm") -> None:
    """Training losses (left, log scale) and the validation metric (right) against the step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    recs = read_log(log)
    train = [r for r in recs if r["kind"] == "train"]
    val = [r for r in recs if r["kind"] == "val"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    keys = [k for k in (train[0] if train else {}) if k not in ("kind", "step", "epoch", "time", "lr")]
    for k in keys:
        ys = [r[k] for r in train]
        if any(y > 0 for y in ys):
            axes[0].plot([r["step"] for r in train], ys, label=k, lw=1)
    axes[0].set_yscale("log")
    axes[0].set_xlabel("step")
    axes[0].set_title("training losses (weighted terms, total)")
    if keys:
        axes[0].legend(fontsize=7)
    for k in [k for k in (val[0] if val else {}) if k.endswith("_mm")]:
        axes[1].plot([r["step"] for r in val], [r[k] for r in val], marker="o", ms=3, label=k)
    axes[1].set_xlabel("step")
    axes[1].set_title(f"validation (mm; best.pt at the lowest {val_metric})")
    if val:
        axes[1].legend(fontsize=7)
    axes[1].grid(alpha=0.3)
    fig.tight_layout()
    tmp = Path(png).with_name(f".{Path(png).name}.tmp.png")
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    os.replace(tmp, png)
