"""What a task brings to ``recovery train`` besides its training step (:class:`TaskSpec`), and the
set-up steps the tasks share.

A task is one kind of network a config's ``task`` names: its module holds the
:class:`recovery.trainer.Task` (networks, optimisers, one training step, validation), a ``setup``
that builds it for a config, and a ``SPEC`` that :mod:`recovery.tasks` registers under its name.
``recovery train`` and the predictor find everything through that registry.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from blsm.io import sha256_file
from recovery import distributed as D
from recovery.config import RecoveryConfig
from recovery.datasets.cache import CropCache, build_caches
from recovery.datasets.loaders import loaders
from recovery.utils.geometry import translation_to_cam
from synth.dataset.crops import crop_affine


@dataclass(frozen=True)
class TaskSpec:
    """One task of :data:`recovery.tasks.TASKS`.

    Attributes:
        name: the config's ``task`` (and the checkpoint's).
        setup: ``(cfg, log) -> (task, train, val)``: the :class:`recovery.trainer.Task` built for
            the config, with its training and validation caches (None for a task that reads no
            images).
        batches: ``(cfg, task, train, val, env) -> (make_loader, val_loader, epoch_size)``: the
            training batches from a position of the data order (:class:`recovery.trainer.Trainer`'s
            ``make_loader``), what ``validate`` reads, and the items of an epoch.
        best_metric: the validation metric whose minimum writes ``best.pt``.
        describe: ``(cfg, train, val, env, epoch_size) -> str``: the run's first log line.
        distributed: whether it trains under ``torchrun`` (several processes).
        network: the key of :meth:`recovery.trainer.Task.modules` that holds the network (what
            ``train.init`` loads and inference reads from a checkpoint).

    The network a checkpoint of the task holds for inference is registered apart, in
    :data:`recovery.models.registry.NETWORKS`, so that inference imports no training module.
    """

    name: str
    setup: Callable[[RecoveryConfig, Any], tuple[Any, CropCache | None, CropCache | None]]
    batches: Callable[..., tuple[Any, Any, int]]
    best_metric: str
    describe: Callable[..., str]
    distributed: bool = False
    network: str = "model"


def set_threads(cfg: RecoveryConfig) -> None:
    """``train.threads``: torch's CPU threads (0 keeps torch's default)."""
    if cfg.train.threads:
        torch.set_num_threads(cfg.train.threads)


def open_caches(cfg: RecoveryConfig, log: Any = print) -> tuple[CropCache, CropCache | None]:
    """The training and validation caches of ``cfg.data`` (built when missing or stale), and torch
    seeded with ``train.seed`` after building them (building one draws from torch's RNG)."""
    train_dirs, val_dir = build_caches(cfg.data, log)
    torch.manual_seed(cfg.train.seed)
    train = CropCache(train_dirs)
    val = CropCache([val_dir]) if val_dir is not None else None
    return train, val


def checkpoint_meta(cfg: RecoveryConfig, model_path: Path) -> dict[str, Any]:
    """What a checkpoint is made for: the BLSM model file's hash and the network settings' hash."""
    return {"blsm_model_sha256": sha256_file(model_path), "model_hash": cfg.model_hash()}


def mesh_statistics(cfg: RecoveryConfig, body: nn.Module, path: Path,
                    log: Any = print) -> tuple[Any, torch.Tensor, torch.Tensor]:
    """The operators and the training meshes' statistics (mean, std) of the spiral networks."""
    from recovery.datasets.meshes import MeshSource, fixed_meshes, vertex_stats
    from recovery.mesh.operators import mesh_operators

    ops = mesh_operators(path, cfg.mesh.cache, cfg.mesh.ops_settings(), log=log)
    source = MeshSource(body, cfg.meshes, "train")
    meshes = fixed_meshes(body, source, cfg.meshes.stats_meshes, cfg.train.seed + 1)
    mean, std = vertex_stats(meshes)
    return ops, mean, std


def image_batches(cfg: RecoveryConfig, task: Any, train: CropCache, val: CropCache | None,
                  env: D.DistEnv = D.SINGLE) -> tuple[Any, Any, int]:
    """:func:`recovery.datasets.loaders.loaders` and an epoch of the training caches' people."""
    make_loader, val_loader = loaders(cfg, task, train, val, env)
    return make_loader, val_loader, len(train)


def describe_images(cfg: RecoveryConfig, train: CropCache, val: CropCache | None, env: D.DistEnv,
                    epoch_size: int) -> str:
    """The first log line of a run on images: people, datasets, validation people, backbone, steps."""
    part = cfg.train.batch_size // env.world_size
    procs = f" ({env.world_size} processes of {part})" if env.distributed else ""
    return (f"[recovery] {cfg.task}: {len(train)} people from {len(cfg.data.train)} datasets; "
            f"val: {0 if val is None else min(len(val), cfg.data.max_val or len(val))} people; "
            f"{cfg.model.backbone}, {cfg.train.steps} steps of {cfg.train.batch_size}{procs}")


def label_cams(ds: CropCache, crop: int) -> torch.Tensor:
    """(N, 3) the weak-perspective cameras ``(s, tx, ty)`` of a cache's labels at its un-augmented
    ``crop``-pixel crop (:func:`recovery.utils.geometry.translation_to_cam`)."""
    side = ds.side
    a = torch.tensor(crop_affine((side / 2, side / 2), side / ds.context, crop), dtype=torch.float32)
    k = a @ torch.from_numpy(ds.label("K_crop")).float()
    return translation_to_cam(torch.from_numpy(ds.label("transl_cam")).float(), k, crop)
