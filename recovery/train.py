"""``recovery train CONFIG --out DIR [--resume]``: caches, mean parameters, real poses, loaders, and the
generic loop on the config's task: HMR-BLSM (``hmr_blsm``), the image-to-mesh network (``mesh``) or
the mesh autoencoder (``autoencoder``, on meshes made without rendering).

Everything the run depends on is a function of the config and its seed: the caches are built once
(:func:`recovery.data.build_cache`), Theta_0 is the training caches' mean, the real poses are drawn
with the seed, and the data order and augmentation come from :class:`recovery.data.ResumableSampler`
and :class:`recovery.data.BatchAugment`.

Under ``torchrun`` (HMR-BLSM only) every process runs this with the same config: rank 0 builds the
caches while the others wait, each process reads its part of every global batch
(:class:`recovery.data.ShardedBatches`), and rank 0 alone prints and writes the run folder
(:mod:`recovery.distributed`, docs/recovery.md).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

import blsm
from blsm.io import sha256_file
from blsm.model import DEFAULT_MODEL
from recovery import distributed as D
from recovery.config import RecoveryConfig
from recovery.data import (
    BatchAugment,
    CropCache,
    ResumableSampler,
    ShardedBatches,
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


def cam_mean(ds: CropCache, crop: int) -> torch.Tensor:
    """(3,) the mean ``(s, tx, ty)`` of the training caches' labels at the un-augmented crop."""
    side = ds.side
    a = torch.tensor(crop_affine((side / 2, side / 2), side / ds.context, crop), dtype=torch.float32)
    k = a @ torch.from_numpy(ds.label("K_crop")).float()
    return translation_to_cam(torch.from_numpy(ds.label("transl_cam")).float(), k, crop).mean(0)


def mesh_setup(cfg: RecoveryConfig, body: Any, path: Path, log: Any = print) -> tuple[Any, torch.Tensor, torch.Tensor]:
    """The operators and the training meshes' statistics (mean, std) of the spiral networks."""
    from recovery.mesh.operators import mesh_operators
    from recovery.mesh_data import MeshSource, fixed_meshes, vertex_stats

    ops = mesh_operators(path, cfg.mesh.cache, cfg.mesh.ops_settings(), log=log)
    meshes = fixed_meshes(body, MeshSource(body, cfg.meshes, "train"), cfg.meshes.stats_meshes, cfg.train.seed + 1)
    mean, std = vertex_stats(meshes)
    return ops, mean, std


def setup(cfg: RecoveryConfig, log: Any = print) -> tuple[Any, CropCache | None, CropCache | None]:
    """The task with its model, caches and real poses for ``cfg``."""
    if cfg.task == "autoencoder":
        return setup_autoencoder(cfg, log), None, None
    if cfg.task == "mesh":
        return setup_mesh(cfg, log)
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


def setup_autoencoder(cfg: RecoveryConfig, log: Any = print) -> Any:
    from recovery.ae_task import AutoencoderTask

    if cfg.train.threads:
        torch.set_num_threads(cfg.train.threads)
    torch.manual_seed(cfg.train.seed)
    path = model_file(cfg)
    body = blsm.load(path)
    ops, mean, std = mesh_setup(cfg, body, path, log)
    meta = {"blsm_model_sha256": sha256_file(path), "model_hash": cfg.model_hash()}
    return AutoencoderTask(cfg, body, ops, mean, std, meta)


def setup_mesh(cfg: RecoveryConfig, log: Any = print) -> tuple[Any, CropCache, CropCache | None]:
    from recovery.mesh_task import MeshTask

    if cfg.train.threads:
        torch.set_num_threads(cfg.train.threads)
    train_dirs, val_dir = caches(cfg, log)
    torch.manual_seed(cfg.train.seed)
    train = CropCache(train_dirs)
    val = CropCache([val_dir]) if val_dir is not None else None
    path = model_file(cfg)
    body = blsm.load(path)
    ops, mean, std = mesh_setup(cfg, body, path, log)
    torch.manual_seed(cfg.train.seed)  # the statistics' draws must not change the initialisation
    meta = {"blsm_model_sha256": sha256_file(path), "model_hash": cfg.model_hash()}
    task = MeshTask(cfg, body, ops, mean, std, cam_mean(train, cfg.data.crop), train.keypoint_names, meta)
    return task, train, val


def mesh_loaders(cfg: RecoveryConfig, task: Any) -> tuple[Any, Any, int]:
    """The autoencoder's endless training batches and fixed validation meshes."""
    from recovery.mesh_data import MeshSource, fixed_meshes, mesh_batches

    bs = cfg.train.batch_size
    source = MeshSource(task.body, cfg.meshes, "train")

    def make_loader(consumed: int) -> Any:
        return mesh_batches(source, bs, cfg.train.seed, start=consumed // bs)

    val = fixed_meshes(task.body, MeshSource(task.body, cfg.meshes, "val"), cfg.meshes.val_meshes, cfg.train.seed + 2)
    return make_loader, list(val.split(64)), len(source.people)


def loaders(cfg: RecoveryConfig, task: Any, train: CropCache, val: CropCache | None,
            env: D.DistEnv = D.SINGLE) -> tuple[Any, Any]:
    """The training batches from a position of the global order (this process' part of each
    global batch) and the validation loader."""
    d = cfg.data
    aug = BatchAugment(d.crop, train.context, augment_config(d.augment), cfg.train.seed, task.body.dof_mirror,
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


def train(cfg: RecoveryConfig, out: str | Path, resume: bool = False, log: Any = print) -> str:
    """Run (or continue) a training run into ``out``; returns "done" or "interrupted".

    Under ``torchrun`` (``WORLD_SIZE`` > 1) this process joins the process group for the run and
    leaves it at the end (module docstring).
    """
    env = D.from_environment()
    if env.distributed and cfg.task != "hmr_blsm":
        raise ValueError(f"task {cfg.task} trains on one process only; run it without torchrun")
    if cfg.train.batch_size % env.world_size:
        raise ValueError(f"train.batch_size {cfg.train.batch_size} (the global batch) must be divisible by "
                         f"the {env.world_size} processes")
    device = D.init(env, resolve_device(cfg.train.device))
    try:
        return _train(cfg, Path(out), resume, log if env.main else (lambda *a: None), env, device)
    finally:
        D.shutdown()


def _train(cfg: RecoveryConfig, out: Path, resume: bool, log: Any, env: D.DistEnv,
           device: torch.device) -> str:
    last = out / "last.pt"
    if last.is_file() and not resume:
        raise ValueError(f"{last}: a run exists here; use --resume to continue it or another --out")
    if env.distributed:  # one writer per cache: rank 0 builds, the others then find them complete
        if env.main:
            caches(cfg, log)
        D.barrier()
    task, train_ds, val_ds = setup(cfg, log)
    if cfg.task == "autoencoder":
        make_loader, val_loader, epoch_size = mesh_loaders(cfg, task)
    else:
        make_loader, val_loader = loaders(cfg, task, train_ds, val_ds, env)
        epoch_size = len(train_ds)
    trainer = Trainer(task, out, make_loader, val_loader, steps=cfg.train.steps, batch_size=cfg.train.batch_size,
                      val_every=cfg.train.val_every, checkpoint_every=cfg.train.checkpoint_every,
                      log_every=cfg.train.log_every, config=cfg.to_dict(), epoch_size=epoch_size,
                      device=device, best_metric="vertex_mm" if cfg.task == "autoencoder" else "pa_mpjpe_mm",
                      env=env, seed=cfg.train.seed)
    if resume and last.is_file():
        trainer.resume(last)
        log(f"[recovery] resumed {last} at step {trainer.step}")
    elif resume:
        log(f"[recovery] {last}: nothing to resume; starting")
    if cfg.task == "autoencoder":
        log(f"[recovery] autoencoder: meshes of {epoch_size} population members, {cfg.train.steps} steps of {cfg.train.batch_size}")
    else:
        part = cfg.train.batch_size // env.world_size
        procs = f" ({env.world_size} processes of {part})" if env.distributed else ""
        log(f"[recovery] {cfg.task}: {len(train_ds)} people from {len(cfg.data.train)} datasets; "
            f"val: {0 if val_ds is None else min(len(val_ds), cfg.data.max_val or len(val_ds))} people; "
            f"{cfg.model.backbone}, {cfg.train.steps} steps of {cfg.train.batch_size}{procs}")
    return trainer.run()
