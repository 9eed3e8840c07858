"""The batches a training run reads: augmented crops of the caches in the run's resumable order (the
image networks), or BLSM meshes drawn without rendering (the mesh autoencoder)."""

from __future__ import annotations

from typing import Any

import torch

from recovery import distributed as D
from recovery.config import RecoveryConfig
from recovery.datasets.augment import BatchAugment
from recovery.datasets.cache import CropCache
from recovery.datasets.meshes import MeshSource, fixed_meshes, mesh_batches
from recovery.datasets.sampling import ResumableSampler, ShardedBatches, spread_indices


def loaders(cfg: RecoveryConfig, task: Any, train: CropCache, val: CropCache | None,
            env: D.DistEnv = D.SINGLE) -> tuple[Any, Any]:
    """The training batches from a position of the global order (this process' part of each
    global batch) and the validation loader."""
    d = cfg.data
    aug = BatchAugment(d.crop, train.context, d.augment, cfg.train.seed, task.body.dof_mirror,
                       train.keypoint_names, effects=d.effects)

    def make_loader(consumed: int) -> Any:
        n = len(train)
        sampler = ResumableSampler(n, cfg.train.seed, consumed // n, consumed % n)
        batches = ShardedBatches(sampler, cfg.train.batch_size, env.rank, env.world_size)
        dl = torch.utils.data.DataLoader(train, batch_sampler=batches, collate_fn=aug, num_workers=d.workers,
                                         persistent_workers=False, prefetch_factor=4 if d.workers else None)
        return iter(dl)

    val_loader = None
    if val is not None:
        vaug = BatchAugment(d.crop, val.context, None, 0, task.body.dof_mirror, val.keypoint_names)
        sub = torch.utils.data.Subset(val, spread_indices(len(val), d.max_val).tolist())
        val_loader = torch.utils.data.DataLoader(sub, batch_size=64, shuffle=False, collate_fn=vaug, num_workers=0)
    return make_loader, val_loader


def mesh_loaders(cfg: RecoveryConfig, task: Any) -> tuple[Any, Any, int]:
    """The autoencoder's endless training batches and fixed validation meshes."""
    bs = cfg.train.batch_size
    source = MeshSource(task.body, cfg.meshes, "train")

    def make_loader(consumed: int) -> Any:
        return mesh_batches(source, bs, cfg.train.seed, start=consumed // bs)

    val = fixed_meshes(task.body, MeshSource(task.body, cfg.meshes, "val"), cfg.meshes.val_meshes, cfg.train.seed + 2)
    return make_loader, list(val.split(64)), len(source.people)
