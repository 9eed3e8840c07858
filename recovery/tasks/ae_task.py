"""The mesh autoencoder's training step (thesis Sec. 4.3.3, Eq. 4.5), apart from the generic loop.

Each step draws a batch of body-frame BLSM meshes (:mod:`recovery.datasets.meshes`), normalises them
with the training meshes' statistics and takes one Adam step on the L1 reconstruction error of the
normalised vertices. Validation reports the mean Euclidean vertex error in millimetres on the
fixed validation meshes (``vertex_mm``).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

import blsm
from blsm.spiral.hierarchy import MeshOperators
from recovery.config import RecoveryConfig, model_file
from recovery.datasets.loaders import mesh_loaders
from recovery.datasets.meshes import body_frame_vertices
from recovery.eval.metrics import vertex_error_mm
from recovery.models import losses as L
from recovery.models.mesh_ae import MeshAutoencoder
from recovery.tasks.base import TaskSpec, checkpoint_meta, mesh_statistics, set_threads
from recovery.utils.schedule import warmup_cosine


class AutoencoderTask:
    """The autoencoder :class:`recovery.trainer.Task`.

    Args:
        cfg: the run's configuration (``task: autoencoder``).
        body: the BLSM model (makes the meshes).
        ops: the template's operators.
        mean, std: (V, 3) the training meshes' statistics.
        meta: what a checkpoint is made for (model file hash, ...).
    """

    name = "autoencoder"

    def __init__(self, cfg: RecoveryConfig, body: nn.Module, ops: MeshOperators, mean: torch.Tensor,
                 std: torch.Tensor, meta: dict[str, Any]) -> None:
        self.cfg, self.body, self.meta = cfg, body, meta
        m = cfg.mesh
        self.model = MeshAutoencoder(ops, mean, std, tuple(m.channels), m.latent)
        o = cfg.optim
        self.opt = torch.optim.Adam(self.model.parameters(), lr=o.lr, weight_decay=o.weight_decay)
        self.sched = torch.optim.lr_scheduler.LambdaLR(
            self.opt, lambda s: warmup_cosine(s, cfg.train.steps, o.warmup_steps, o.schedule))
        self.device = torch.device("cpu")

    def modules(self) -> dict[str, nn.Module]:
        return {"ae": self.model}

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"ae": self.opt}

    def schedulers(self) -> dict[str, Any]:
        return {"ae": self.sched}

    def extra_state(self) -> dict[str, Any]:
        return {}

    def load_extra_state(self, state: dict[str, Any]) -> None:
        pass

    def checkpoint_meta(self) -> dict[str, Any]:
        return dict(self.meta)

    def to(self, device: torch.device) -> None:
        self.device = device
        self.body.to(device)
        self.model.to(device)

    def training_step(self, batch: dict[str, torch.Tensor], step: int) -> dict[str, float]:
        with torch.no_grad():
            v = body_frame_vertices(self.body, batch["pose"].to(self.device), batch["bone"].to(self.device),
                                    batch["shape"].to(self.device))
        self.model.train()
        x = self.model.normalizer(v)
        loss = (self.model(x) - x).abs().mean()  # Eq. 4.5 (mean instead of sum: a scale of the rate)
        L.check_finite({"l1": loss}, step, batch["key"])
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        if self.cfg.optim.grad_clip:
            nn.utils.clip_grad_norm_(self.model.parameters(), self.cfg.optim.grad_clip)
        self.opt.step()
        self.sched.step()
        return {"l1": float(loss.detach()), "lr": float(self.sched.get_last_lr()[0])}

    @torch.no_grad()
    def validate(self, meshes: Any) -> dict[str, float]:
        """``meshes``: batches (B, V, 3) of body-frame meshes -> mean vertex error (mm)."""
        self.model.eval()
        errs = [vertex_error_mm(self.model.reconstruct(v.to(self.device)), v.to(self.device)) for v in meshes]
        return {"vertex_mm": float(torch.cat(errs).mean())}


def setup(cfg: RecoveryConfig, log: Any = print) -> tuple[AutoencoderTask, None, None]:
    """The autoencoder task with its model for ``cfg`` (it reads no images)."""
    set_threads(cfg)
    torch.manual_seed(cfg.train.seed)
    path = model_file(cfg)
    body = blsm.load(path)
    ops, mean, std = mesh_statistics(cfg, body, path, log)
    return AutoencoderTask(cfg, body, ops, mean, std, checkpoint_meta(cfg, path)), None, None


def batches(cfg: RecoveryConfig, task: AutoencoderTask, train: None, val: None,
            env: Any) -> tuple[Any, Any, int]:
    """Endless batches of meshes, fixed validation meshes, and the training population's size."""
    return mesh_loaders(cfg, task)


def describe(cfg: RecoveryConfig, train: None, val: None, env: Any, epoch_size: int) -> str:
    return (f"[recovery] autoencoder: meshes of {epoch_size} population members, {cfg.train.steps} steps of "
            f"{cfg.train.batch_size}")


SPEC = TaskSpec(name=AutoencoderTask.name, setup=setup, batches=batches, best_metric="vertex_mm",
                describe=describe, distributed=False, network="ae")
