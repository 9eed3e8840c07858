"""``recovery train CONFIG --out DIR [--resume]``: the config's task (:mod:`recovery.tasks`) set up,
its batches, and the generic loop (:mod:`recovery.trainer`): HMR-BLSM (``hmr_blsm``), the
image-to-mesh network (``mesh``) or the mesh autoencoder (``autoencoder``, on meshes made without
rendering).

Everything the run depends on is a function of the config and its seed: the caches are built once
(:func:`recovery.datasets.cache.build_cache`), Theta_0 is the training caches' mean, the real poses
are drawn with the seed, and the data order and augmentation come from
:class:`recovery.datasets.sampling.ResumableSampler` and
:class:`recovery.datasets.augment.BatchAugment`.

Under ``torchrun`` (HMR-BLSM only) every process runs this with the same config: rank 0 builds the
caches while the others wait, each process reads its part of every global batch
(:class:`recovery.datasets.sampling.ShardedBatches`), and rank 0 alone prints and writes the run
folder (:mod:`recovery.distributed`, docs/recovery.md).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from blsm.io import sha256_file
from recovery import distributed as D
from recovery.checkpoint import module_state, network_hash, read_checkpoint, resolve
from recovery.config import TASK_SECTIONS, RecoveryConfig, model_file
from recovery.datasets.cache import CropCache, build_caches
from recovery.models.backbones import check_backbone
from recovery.tasks import get_task
from recovery.trainer import Trainer


def resolve_device(name: str) -> torch.device:
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("train.device is cuda but no CUDA device is available")
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def setup(cfg: RecoveryConfig, log: Any = print) -> tuple[Any, CropCache | None, CropCache | None]:
    """The task with its model, caches and real poses for ``cfg``."""
    return get_task(cfg.task).setup(cfg, log)


def train(cfg: RecoveryConfig, out: str | Path, resume: bool = False, log: Any = print) -> str:
    """Run (or continue) a training run into ``out``; returns "done" or "interrupted".

    Under ``torchrun`` (``WORLD_SIZE`` > 1) this process joins the process group for the run and
    leaves it at the end (module docstring).
    """
    env = D.from_environment()
    if env.distributed and not get_task(cfg.task).distributed:
        raise ValueError(f"task {cfg.task} trains on one process only; run it without torchrun")
    if cfg.train.batch_size % env.world_size:
        raise ValueError(f"train.batch_size {cfg.train.batch_size} (the global batch) must be divisible by "
                         f"the {env.world_size} processes")
    device = D.init(env, resolve_device(cfg.train.device))
    try:
        return _train(cfg, Path(out), resume, log if env.main else (lambda *a: None), env, device)
    finally:
        D.shutdown()


def preflight(cfg: RecoveryConfig, resume: bool = False) -> dict[str, torch.Tensor] | None:
    """What a run needs that its config alone does not say, checked before any cache is built: the
    backbone is registered, and ``train.init`` (unless the run resumes, whose ``last.pt`` holds every
    weight) is a checkpoint of this task's network made with this BLSM model file. Returns the
    network weights of ``train.init`` (float32) or None; a ValueError names the file otherwise."""
    if "model" in TASK_SECTIONS[cfg.task]:
        check_backbone(cfg.model.backbone)
    if not cfg.train.init or resume:
        return None
    path = resolve(cfg.train.init)
    ck = read_checkpoint(path)
    network = get_task(cfg.task).network
    if ck.get("task", "hmr_blsm") != cfg.task or network_hash(ck) != cfg.model_hash() or network not in ck.get("modules", {}):
        raise ValueError(f"{path}: train.init is not a checkpoint of this network (task or model settings differ)")
    if ck.get("blsm_model_sha256") != sha256_file(model_file(cfg)):
        raise ValueError(f"{path}: train.init was made with another BLSM model file")
    return module_state(ck, network)


def _train(cfg: RecoveryConfig, out: Path, resume: bool, log: Any, env: D.DistEnv,
           device: torch.device) -> str:
    last = out / "last.pt"
    if last.is_file() and not resume:
        raise ValueError(f"{last}: a run exists here; use --resume to continue it or another --out")
    init = preflight(cfg, resume and last.is_file())
    if env.distributed:  # one writer per cache: rank 0 builds, the others then find them complete
        if env.main:
            build_caches(cfg.data, log)
        D.barrier()
    spec = get_task(cfg.task)
    task, train_ds, val_ds = spec.setup(cfg, log)
    if init is not None:  # train.init, for every task: the network's weights, before anything trains
        try:
            task.modules()[spec.network].load_state_dict(init)
        except RuntimeError as exc:
            raise ValueError(f"{cfg.train.init}: train.init's weights do not fit this network "
                             f"({str(exc).splitlines()[0][:160]})") from None
    make_loader, val_loader, epoch_size = spec.batches(cfg, task, train_ds, val_ds, env)
    trainer = Trainer(task, out, make_loader, val_loader, steps=cfg.train.steps, batch_size=cfg.train.batch_size,
                      val_every=cfg.train.val_every, checkpoint_every=cfg.train.checkpoint_every,
                      log_every=cfg.train.log_every, config=cfg.to_dict(), epoch_size=epoch_size,
                      device=device, best_metric=spec.best_metric, env=env, seed=cfg.train.seed)
    if resume and last.is_file():
        trainer.resume(last)
        log(f"[recovery] resumed {last} at step {trainer.step}")
    elif resume:
        log(f"[recovery] {last}: nothing to resume; starting")
    log(spec.describe(cfg, train_ds, val_ds, env, epoch_size))
    return trainer.run()
