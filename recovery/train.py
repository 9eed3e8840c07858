"""``recovery train CONFIG --out DIR [--resume]``: caches, mean parameters, real poses, loaders, and the
generic loop on HMR-BLSM's task.

Everything the run depends on is a function of the config and its seed: the caches are built once
(:func:`recovery.data.build_cache`), Theta_0 is the training caches' mean, the real poses are drawn
with the seed, and the data order and augmentation come from :class:`recovery.data.ResumableSampler`
and :class:`recovery.data.BatchAugment`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

import blsm
from blsm.io import sha256_file
from blsm.model import DEFAULT_MODEL
from recovery.config import RecoveryConfig
from recovery.data import (
    BatchAugment,
    CropCache,
    ResumableSampler,
    augment_config,
    build_cache,
    cache_folder,
    real_poses,
    spread_indices,
)
from recovery.geometry import translation_to_cam
from recovery.hmr_task import HMRTask
from recovery.models.hmr import ParamLayout, mean_theta
from recovery.trainer import Trainer
from synth.data import crop_affine


def model_file(cfg: RecoveryConfig) -> Path:
    return Path(cfg.model.blsm_model) if cfg.model.blsm_model else DEFAULT_MODEL


def resolve_device(name: str) -> torch.device:
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("train.device is cuda but no CUDA device is available")
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def caches(cfg: RecoveryConfig, log: Any = print) -> tuple[list[Path], Path | None]:
    """Build (or reuse) the caches of the training and validation datasets."""
    d = cfg.data
    for path in (*d.train, *([d.val] if d.val else [])):
        if not Path(path).is_dir():
            raise ValueError(f"{path}: no such dataset folder")
    train = [build_cache(p, cache_folder(p, d.cache, d.crop, d.context), d.crop, d.context, log=log) for p in d.train]
    val = build_cache(d.val, cache_folder(d.val, d.cache, d.crop, d.context), d.crop, d.context, log=log) if d.val else None
    return train, val


def theta0(ds: CropCache, layout: ParamLayout, crop: int) -> torch.Tensor:
    """Theta_0 from the training caches' labels at the un-augmented crop."""
    side = ds.side
    a = torch.tensor(crop_affine((side / 2, side / 2), side / ds.context, crop), dtype=torch.float32)
    k = a @ torch.from_numpy(ds.label("K_crop")).float()
    transl = torch.from_numpy(ds.label("transl_cam")).float()
    cam = translation_to_cam(transl, k, crop)
    return mean_theta(layout, torch.from_numpy(ds.label("pose")), torch.from_numpy(ds.label("bone")),
                      torch.from_numpy(ds.label("shape")), cam)


def setup(cfg: RecoveryConfig, log: Any = print) -> tuple[HMRTask, CropCache, CropCache | None]:
    """The task with its model, caches and real poses for ``cfg``."""
    if cfg.train.threads:
        torch.set_num_threads(cfg.train.threads)
    train_dirs, val_dir = caches(cfg, log)
    torch.manual_seed(cfg.train.seed)  # after the caches: building one draws from torch's RNG
    train = CropCache(train_dirs)
    val = CropCache([val_dir]) if val_dir is not None else None
    path = model_file(cfg)
    body = blsm.load(path)
    layout = ParamLayout(body.num_dofs, body.num_bone_coeffs, cfg.model.num_shape)
    init = theta0(train, layout, cfg.data.crop)
    real = None
    d = cfg.discriminator
    if d.enabled:
        real = real_poses(body, d.prior, d.prior_samples, d.library, d.exclude_clips, cfg.train.seed)
        log(f"[recovery] real poses for the discriminator: {real.sources}")
    meta = {"blsm_model_sha256": sha256_file(path), "model_hash": cfg.model_hash()}
    task = HMRTask(cfg, body, init, real, train.keypoint_names, meta)
    return task, train, val


def loaders(cfg: RecoveryConfig, task: HMRTask, train: CropCache, val: CropCache | None) -> tuple[Any, Any]:
    d = cfg.data
    aug = BatchAugment(d.crop, train.context, augment_config(d.augment), cfg.train.seed, task.body.dof_mirror,
                       train.keypoint_names)

    def make_loader(consumed: int) -> Any:
        n = len(train)
        sampler = ResumableSampler(n, cfg.train.seed, consumed // n, consumed % n)
        dl = torch.utils.data.DataLoader(train, batch_size=cfg.train.batch_size, sampler=sampler, collate_fn=aug,
                                         num_workers=d.workers, persistent_workers=False, prefetch_factor=4 if d.workers else None)
        return iter(dl)

    val_loader = None
    if val is not None:
        vaug = BatchAugment(d.crop, val.context, None, 0, task.body.dof_mirror, val.keypoint_names)
        sub = torch.utils.data.Subset(val, spread_indices(len(val), d.max_val).tolist())
        val_loader = torch.utils.data.DataLoader(sub, batch_size=64, shuffle=False, collate_fn=vaug, num_workers=0)
    return make_loader, val_loader


def train(cfg: RecoveryConfig, out: str | Path, resume: bool = False, log: Any = print) -> str:
    """Run (or continue) a training run into ``out``; returns "done" or "interrupted"."""
    out = Path(out)
    last = out / "last.pt"
    if last.is_file() and not resume:
        raise ValueError(f"{last}: a run exists here; use --resume to continue it or another --out")
    task, train_ds, val_ds = setup(cfg, log)
    make_loader, val_loader = loaders(cfg, task, train_ds, val_ds)
    trainer = Trainer(task, out, make_loader, val_loader, steps=cfg.train.steps, batch_size=cfg.train.batch_size,
                      val_every=cfg.train.val_every, checkpoint_every=cfg.train.checkpoint_every,
                      log_every=cfg.train.log_every, config=cfg.to_dict(), epoch_size=len(train_ds),
                      device=resolve_device(cfg.train.device))
    if resume and last.is_file():
        trainer.resume(last)
        log(f"[recovery] resumed {last} at step {trainer.step}")
    elif resume:
        log(f"[recovery] {last}: nothing to resume; starting")
    log(f"[recovery] train: {len(train_ds)} people from {len(cfg.data.train)} datasets; "
        f"val: {0 if val_ds is None else min(len(val_ds), cfg.data.max_val or len(val_ds))} people; "
        f"{cfg.model.backbone}, {cfg.train.steps} steps of {cfg.train.batch_size}")
    return trainer.run()
