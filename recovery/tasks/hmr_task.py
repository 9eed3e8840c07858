"""HMR-BLSM's training step, apart from the generic loop (:mod:`recovery.trainer`).

One step: the regressor's forward on the augmented crops, BLSM on its last IEF estimate, the losses
of :class:`recovery.config.LossConfig`, one AdamW update of the regressor (gradient clipping,
warm-up then cosine schedule), then, with the discriminator on, one Adam update of the 47-D pose
discriminator on real poses (:func:`recovery.datasets.real_poses.real_poses`) against the detached
predictions (least squares, HMR Eq. 6). A NaN or infinite loss stops training with the step and the batch's
sample keys ``(epoch, item, dataset, sample index, person)``.

With several processes (:mod:`recovery.distributed`) each rank steps on its part of the global batch:
the regressor inside DistributedDataParallel (BatchNorm synchronised with
``train.sync_batchnorm``), each loss term given as the rank's share (:func:`recovery.distributed.
share_normaliser` for the 2D keypoints, whose count of visible keypoints varies), the real poses
drawn for the global batch and split like it, and the discriminator's gradients averaged over the
ranks; the logged values are the global ones, equal on every rank.
"""

from __future__ import annotations

import contextlib
from typing import Any

import torch
from torch import nn

import blsm
from blsm.joint_limits import angles_from_unconstrained
from recovery import distributed as D
from recovery.config import RecoveryConfig, model_file
from recovery.datasets.cache import CropCache
from recovery.datasets.real_poses import RealPoses, real_poses
from recovery.eval import metrics as M
from recovery.eval.joints import PELVIS, indices
from recovery.models import losses as L
from recovery.models.discriminator import PoseDiscriminator, normalise_angles
from recovery.models.heads import ParamLayout, mean_theta
from recovery.models.hmr import body_outputs, predict_body
from recovery.models.registry import build_hmr
from recovery.tasks.base import (
    TaskSpec,
    checkpoint_meta,
    describe_images,
    image_batches,
    label_cams,
    open_caches,
    set_threads,
)
from recovery.utils.schedule import warmup_cosine


class HMRTask:
    """The HMR-BLSM :class:`recovery.trainer.Task`.

    Args:
        cfg: the run's configuration.
        body: the BLSM model (frozen; moved with the task).
        init: (P,) Theta_0, the training set's mean parameters.
        real: the discriminator's real poses (None without discriminator).
        keypoint_names: the datasets' keypoint names (must be the model's).
        crop: the network's input side, pixels.
        checkpoint_meta: identifies what a checkpoint was made for (model file hash, ...).
    """

    name = "hmr_blsm"

    def __init__(self, cfg: RecoveryConfig, body: nn.Module, init: torch.Tensor, real: RealPoses | None,
                 keypoint_names: list[str], meta: dict[str, Any]) -> None:
        self.cfg, self.body, self.real, self.meta = cfg, body, real, meta
        if list(keypoint_names) != list(body.keypoint_names):
            raise ValueError("the datasets' keypoint_names are not the BLSM model's (made with another model?)")
        self.crop = cfg.data.crop
        self.model = build_hmr(cfg, body, init)
        self.model.backbone.use_channels_last(cfg.train.channels_last)
        self.net: nn.Module = self.model  # the training forward: the DDP wrapper with several processes
        self.world, self.rank = 1, 0
        o = cfg.optim
        groups: Any = self.model.parameters()  # one group, as runs made before optim.backbone_lr
        if o.backbone_lr != 1.0:
            backbone = list(self.model.backbone.parameters())
            ids = {id(p) for p in backbone}
            groups = [{"params": [p for p in self.model.parameters() if id(p) not in ids]},
                      {"params": backbone, "lr": o.lr * o.backbone_lr}]
        self.opt = torch.optim.AdamW(groups, lr=o.lr, weight_decay=o.weight_decay)
        total = cfg.train.steps
        self.sched = torch.optim.lr_scheduler.LambdaLR(
            self.opt, lambda s: warmup_cosine(s, total, o.warmup_steps, o.schedule))
        self.disc: PoseDiscriminator | None = None
        d = cfg.discriminator
        if d.enabled:
            if real is None:
                raise ValueError("the discriminator needs real poses")
            self.disc = PoseDiscriminator(body.dof_limits)
            self.d_opt = torch.optim.Adam(self.disc.parameters(), lr=d.lr, weight_decay=d.weight_decay)
        self.generator = torch.Generator().manual_seed(cfg.train.seed + 7919)  # real-pose draws
        self.eval_idx = torch.tensor(indices(body.keypoint_names))
        self.device = torch.device("cpu")
        self.amp = False

    def _freeze_bn(self) -> None:
        """``train.frozen_bn``: the backbone's BatchNorm layers in eval mode, their affine fixed."""
        for m in self.model.backbone.modules():
            if isinstance(m, nn.modules.batchnorm._BatchNorm):
                m.eval()
                for p in m.parameters():
                    p.requires_grad_(False)

    # -- Task protocol
    def modules(self) -> dict[str, nn.Module]:
        return {"model": self.model, **({"disc": self.disc} if self.disc is not None else {})}

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"model": self.opt, **({"disc": self.d_opt} if self.disc is not None else {})}

    def schedulers(self) -> dict[str, Any]:
        return {"model": self.sched}

    def extra_state(self) -> dict[str, Any]:
        return {"generator": self.generator.get_state()}

    def load_extra_state(self, state: dict[str, Any]) -> None:
        self.generator.set_state(state["generator"])

    def checkpoint_meta(self) -> dict[str, Any]:
        return dict(self.meta)

    def to(self, device: torch.device) -> None:
        self.device = device
        self.body.to(device)
        for m in self.modules().values():
            m.to(device)
        self.amp = device.type == "cuda" and self.cfg.train.bf16

    def distribute(self, env: D.DistEnv, device: torch.device) -> None:
        """The regressor inside DDP (SyncBatchNorm first with ``train.sync_batchnorm``); checkpoints
        keep saving the unwrapped network, whose state dict a single process loads."""
        if self.cfg.train.sync_batchnorm:
            self.model = D.convert_sync_batchnorm(self.model, device)
        self.net = D.wrap(self.model, env, device)
        self.world, self.rank = env.world_size, env.rank

    def _autocast(self) -> Any:
        if self.amp:
            return torch.autocast("cuda", dtype=torch.bfloat16)
        return contextlib.nullcontext()

    # -- one step
    def losses(self, batch: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], Any]:
        """The weighted loss terms of a batch (on the task's device) and the prediction."""
        cfg, w = self.cfg, self.cfg.loss
        with self._autocast():
            pred = self.net(batch["image"]).float()
        out = predict_body(self.body, pred, batch["K_crop"], self.crop)
        # Each term is this rank's share: the mean of the ranks' terms is the global loss (module
        # docstring). The plain means are shares already, the ranks' parts being of equal size.
        terms: dict[str, torch.Tensor] = {}
        if w.keypoints_2d:
            kp2 = batch["keypoints_2d"]
            terms["kp2d"] = w.keypoints_2d * L.keypoint_2d_loss(out.keypoints_2d, kp2, self.crop,
                                                                D.share_normaliser(kp2[..., 2].sum()))
        if w.keypoints_3d:
            terms["kp3d"] = w.keypoints_3d * L.keypoint_3d_loss(out.keypoints_3d, batch["keypoints_3d"])
        limits = self.body.dof_limits
        if w.pose:
            terms["pose"] = w.pose * L.mse(normalise_angles(out.angles, limits), normalise_angles(batch["angles"], limits))
        if w.global_orient:
            terms["orient"] = w.global_orient * L.mse(pred.orient, batch["global_orient"])
        if w.bone:
            terms["bone"] = w.bone * L.mse(pred.bone, batch["bone"])
        if w.shape and cfg.model.num_shape:
            ns = cfg.model.num_shape
            terms["shape"] = w.shape * L.mse(pred.shape[:, :ns], batch["shape"][:, :ns])
        if w.vertices:
            with torch.no_grad():
                gt = body_outputs(self.body, batch["pose"], batch["global_orient"], batch["bone"], batch["shape"])
            terms["verts"] = w.vertices * (out.vertices - gt.vertices).abs().sum(-1).mean()
        if self.disc is not None and w.adversarial:
            fake = self._fake_angles(pred)
            terms["adv"] = w.adversarial * L.lsgan_generator_loss(self.disc(fake))
        return terms, (pred, out)

    def _fake_angles(self, pred: Any) -> torch.Tensor:
        """Angles of the poses the discriminator judges: the last IEF iteration, or all of them."""
        sl = self.model.layout.slices()["pose"]
        thetas = pred.thetas[1:] if self.cfg.loss.all_iterations and pred.thetas.shape[0] > 1 else pred.thetas[-1:]
        x = thetas[..., sl].reshape(-1, self.body.num_dofs)
        return angles_from_unconstrained(x, self.body.dof_limits)

    def training_step(self, batch: dict[str, torch.Tensor], step: int) -> dict[str, float]:
        """One update on this rank's part of the batch; returns the global losses."""
        batch = {k: v.to(self.device, non_blocking=True) for k, v in batch.items()}
        self.model.train()
        if self.cfg.train.frozen_bn:
            self._freeze_bn()
        terms, (pred, _) = self.losses(batch)
        total = torch.stack(list(terms.values())).sum()
        names = [*terms, "total"]
        values = D.rank_mean(torch.stack([*terms.values(), total]).detach())  # (T + 1,) global values
        _check_finite(dict(zip(names, values, strict=True)), step, batch["key"])
        self.opt.zero_grad(set_to_none=True)
        total.backward()  # DDP averages the ranks' gradients: the global loss's gradient
        if self.cfg.optim.grad_clip:
            nn.utils.clip_grad_norm_(self.model.parameters(), self.cfg.optim.grad_clip)
        self.opt.step()
        self.sched.step()
        logs = {k: float(v) for k, v in zip(names, values, strict=True)}
        if self.disc is not None:
            fake = self._fake_angles(pred).detach()
            real = self._real_poses(fake.shape[0])
            d_loss = L.lsgan_discriminator_loss(self.disc(real), self.disc(fake))
            d_value = D.rank_mean(d_loss.detach())
            _check_finite({"disc": d_value}, step, batch["key"])
            self.d_opt.zero_grad(set_to_none=True)
            d_loss.backward()
            D.average_gradients(self.disc.parameters())
            self.d_opt.step()
            logs["disc"] = float(d_value)
        logs["lr"] = float(self.sched.get_last_lr()[0])
        return logs

    def _real_poses(self, n: int) -> torch.Tensor:
        """(n, 47) this rank's real poses: its part of the ``n W`` drawn for the global batch (every
        rank draws them all, so the generator stays the same everywhere and they are the
        single-process draws)."""
        real = self.real.sample(n * self.world, self.generator)
        return real[self.rank * n : (self.rank + 1) * n].to(self.device)

    @torch.no_grad()
    def predict(self, images: torch.Tensor, k_crop: torch.Tensor) -> Any:
        self.model.eval()
        with self._autocast():
            pred = self.model(images.to(self.device)).float()
        return pred, predict_body(self.body, pred, k_crop.to(self.device), self.crop)

    @torch.no_grad()
    def validate(self, loader: Any) -> dict[str, float]:
        """MPJPE (pelvis-aligned), PA-MPJPE on :data:`recovery.eval.joints.EVAL_JOINTS` and PVE, mm."""
        err: dict[str, list[torch.Tensor]] = {"mpjpe_mm": [], "pa_mpjpe_mm": [], "pve_mm": []}
        for batch in loader:
            batch = {k: v.to(self.device) for k, v in batch.items()}
            pred, out = self.predict(batch["image"], batch["K_crop"])
            p3 = out.keypoints_3d[:, self.eval_idx]
            g3 = batch["keypoints_3d"][:, self.eval_idx]
            err["mpjpe_mm"].append(M.mpjpe(M.pelvis_aligned(p3, PELVIS), M.pelvis_aligned(g3, PELVIS)) * 1000)
            err["pa_mpjpe_mm"].append(M.pa_mpjpe(p3, g3) * 1000)
            gt = body_outputs(self.body, batch["pose"], batch["global_orient"], batch["bone"], batch["shape"])
            err["pve_mm"].append(M.mpjpe(out.vertices, gt.vertices) * 1000)
        return {k: float(torch.cat(v).mean()) for k, v in err.items() if v}


def _check_finite(losses: dict[str, torch.Tensor], step: int, keys: torch.Tensor) -> None:
    """:func:`recovery.models.losses.check_finite` of global values: every rank raises at the same step,
    naming the samples of the whole batch."""
    if all(bool(torch.isfinite(v).all()) for v in losses.values()):
        return
    L.check_finite(losses, step, D.gather(keys).cpu())


def theta0(ds: CropCache, layout: ParamLayout, crop: int) -> torch.Tensor:
    """Theta_0 from the training caches' labels at the un-augmented crop."""
    return mean_theta(layout, torch.from_numpy(ds.label("pose")), torch.from_numpy(ds.label("bone")),
                      torch.from_numpy(ds.label("shape")), label_cams(ds, crop))


def setup(cfg: RecoveryConfig, log: Any = print) -> tuple[HMRTask, CropCache, CropCache | None]:
    """The HMR-BLSM task with its model, caches and real poses for ``cfg``."""
    set_threads(cfg)
    train, val = open_caches(cfg, log)
    path = model_file(cfg)
    body = blsm.load(path)
    layout = ParamLayout(body.num_dofs, body.num_bone_coeffs, cfg.model.num_shape)
    init = theta0(train, layout, cfg.data.crop)
    real = None
    d = cfg.discriminator
    if d.enabled:
        real = real_poses(body, d.prior, d.prior_samples, d.library, d.exclude_clips, cfg.train.seed)
        log(f"[recovery] real poses for the discriminator: {real.sources}")
    task = HMRTask(cfg, body, init, real, train.keypoint_names, checkpoint_meta(cfg, path))
    return task, train, val


SPEC = TaskSpec(name=HMRTask.name, setup=setup, batches=image_batches, best_metric="pa_mpjpe_mm",
                describe=describe_images, distributed=True)
