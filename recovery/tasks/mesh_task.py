"""The image-to-mesh network's training step (thesis Sec. 4.4), with the BEGAN mesh discriminator.

Generator step: the network's vertices against the labels' body-frame mesh (L_3D, Eq. 4.7: L1 on
vertices, metres, summed over x, y, z and averaged over vertices), the 2D keypoints of the decoded
vertices through the keypoint regressor ``J`` and the weak-perspective camera against the labels
(L_proj, Eq. 4.8: :func:`recovery.models.losses.keypoint_2d_loss`), optionally camera-frame 3D keypoints,
and with ``began.enabled`` the adversarial term ``L_AE(fake)`` (Eq. 4.11). One Adam update
(thesis: Adam, weight decay 1e-5).

Discriminator step (Eqs. 4.9, 4.10, 4.12): with ``L_AE(V) = mean |V - D_AE(V)|`` on normalised
vertices, ``L_D = L_AE(real) - k_t L_AE(fake)`` (one Adam update unless frozen), then
``k_{t+1} = clip(k_t + lambda_k (gamma L_AE(real) - L_AE(fake)), 0, 1)``. Logged: ``k``, the
BEGAN convergence measure ``M = L_AE(real) + |gamma L_AE(real) - L_AE(fake)|``, ``d_real``,
``d_fake``.
"""

from __future__ import annotations

import contextlib
from typing import Any

import torch
from torch import nn

import blsm
from blsm.spiral.hierarchy import MeshOperators
from recovery.checkpoint import read_checkpoint
from recovery.config import RecoveryConfig, model_file
from recovery.datasets.cache import CropCache
from recovery.datasets.meshes import body_frame_vertices
from recovery.eval import metrics as M
from recovery.eval.joints import PELVIS, indices
from recovery.eval.metrics import vertex_error_mm
from recovery.models import losses as L
from recovery.models.mesh_ae import MeshAutoencoder
from recovery.models.mesh_net import MeshOutput, MeshRegressor, weak_perspective
from recovery.tasks.base import (
    TaskSpec,
    checkpoint_meta,
    describe_images,
    image_batches,
    label_cams,
    mesh_statistics,
    open_caches,
    set_threads,
)
from recovery.utils.schedule import warmup_cosine


def began_k_update(k: float, l_real: float, l_fake: float, lambda_k: float, gamma: float) -> float:
    """Eq. 4.12 with BEGAN's clipping: ``clip(k + lambda_k (gamma L_real - L_fake), 0, 1)``."""
    return min(max(k + lambda_k * (gamma * l_real - l_fake), 0.0), 1.0)


def began_convergence(l_real: float, l_fake: float, gamma: float) -> float:
    """BEGAN's global convergence measure ``L_real + |gamma L_real - L_fake|``."""
    return l_real + abs(gamma * l_real - l_fake)


def load_autoencoder_state(path: str) -> dict[str, torch.Tensor]:
    """The autoencoder weights of a ``task: autoencoder`` checkpoint (one-line error otherwise)."""
    ck = read_checkpoint(path)
    if ck.get("task") != "autoencoder":
        raise ValueError(f"{path}: a checkpoint of task {ck.get('task')!r}, not an autoencoder")
    return ck["modules"]["ae"]


class MeshTask:
    """The image-to-mesh :class:`recovery.trainer.Task` (module docstring).

    Args:
        cfg: the run's configuration (``task: mesh``).
        body: the BLSM model (labels' meshes).
        ops: the template's operators (and the keypoint regressor).
        mean, std: (V, 3) normalisation (replaced by the autoencoder's when one is loaded).
        cam_init: (3,) the training crops' mean ``(s, tx, ty)``.
        keypoint_names: the datasets' keypoint names (must be the model's).
        meta: what a checkpoint is made for.
        pretrained_backbone: override ``model.pretrained`` (False when loading a checkpoint).
    """

    name = "mesh"

    def __init__(self, cfg: RecoveryConfig, body: nn.Module, ops: MeshOperators, mean: torch.Tensor,
                 std: torch.Tensor, cam_init: torch.Tensor, keypoint_names: list[str], meta: dict[str, Any],
                 pretrained_backbone: bool | None = None) -> None:
        self.cfg, self.body, self.meta = cfg, body, meta
        if list(keypoint_names) != list(body.keypoint_names) or list(ops.keypoint_names) != list(body.keypoint_names):
            raise ValueError("the datasets' keypoint_names are not the BLSM model's (made with another model?)")
        m, b = cfg.mesh, cfg.began
        self.crop = cfg.data.crop
        ae_state = load_autoencoder_state(m.autoencoder) if m.autoencoder else None
        if ae_state is not None:
            mean, std = ae_state["normalizer.mean"], ae_state["normalizer.std"]
        self.model = MeshRegressor(cfg.model.backbone, ops, mean, std, cam_init,
                                   pretrained=cfg.model.pretrained if pretrained_backbone is None else pretrained_backbone,
                                   channels=tuple(m.channels), latent=m.latent, hidden=m.hidden)
        self.model.backbone.use_channels_last(cfg.train.channels_last)
        if ae_state is not None:
            self.model.decoder.load_state_dict({k[len("decoder."):]: v for k, v in ae_state.items() if k.startswith("decoder.")})
        if m.freeze_decoder:
            self.model.decoder.requires_grad_(False)
        self.regressor = torch.as_tensor(ops.regressor)  # (K, V)
        o = cfg.optim
        params = [p for p in self.model.parameters() if p.requires_grad]
        self.opt = torch.optim.Adam(params, lr=o.lr, weight_decay=o.weight_decay)
        self.sched = torch.optim.lr_scheduler.LambdaLR(
            self.opt, lambda s: warmup_cosine(s, cfg.train.steps, o.warmup_steps, o.schedule))
        self.disc: MeshAutoencoder | None = None
        self.d_opt: torch.optim.Optimizer | None = None
        self.k = float(b.k0)
        if b.enabled:
            self.disc = MeshAutoencoder(ops, self.model.normalizer.mean, self.model.normalizer.std, tuple(m.channels), m.latent)
            if b.pretrained and ae_state is not None:
                self.disc.load_state_dict(ae_state)
            if b.freeze:
                self.disc.requires_grad_(False)
            else:
                self.d_opt = torch.optim.Adam(self.disc.parameters(), lr=b.lr, weight_decay=b.weight_decay)
        self.eval_idx = torch.tensor(indices(body.keypoint_names))
        self.pelvis = int(self.eval_idx[PELVIS])
        self.device = torch.device("cpu")
        self.amp = False

    # -- Task protocol
    def modules(self) -> dict[str, nn.Module]:
        return {"model": self.model, **({"disc": self.disc} if self.disc is not None else {})}

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"model": self.opt, **({"disc": self.d_opt} if self.d_opt is not None else {})}

    def schedulers(self) -> dict[str, Any]:
        return {"model": self.sched}

    def extra_state(self) -> dict[str, Any]:
        return {"k": self.k}

    def load_extra_state(self, state: dict[str, Any]) -> None:
        self.k = float(state["k"])

    def checkpoint_meta(self) -> dict[str, Any]:
        return dict(self.meta)

    def to(self, device: torch.device) -> None:
        self.device = device
        self.body.to(device)
        self.regressor = self.regressor.to(device)
        for mod in self.modules().values():
            mod.to(device)
        self.amp = device.type == "cuda" and self.cfg.train.bf16

    def _autocast(self) -> Any:
        return torch.autocast("cuda", dtype=torch.bfloat16) if self.amp else contextlib.nullcontext()

    # -- geometry
    def keypoints(self, vertices: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) -> (B, K, 3) through the keypoint regressor, relative to its pelvis."""
        kp = torch.einsum("kv,bvc->bkc", self.regressor.to(vertices.dtype), vertices)
        return kp - kp[:, self.pelvis: self.pelvis + 1]

    def _ae_loss(self, v: torch.Tensor) -> torch.Tensor:
        """Eq. 4.9 on metres: L1 between the normalised mesh and its reconstruction (per mesh)."""
        x = self.disc.normalizer(v)
        return (x - self.disc(x)).abs().mean(dim=(1, 2))

    def losses(self, batch: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], MeshOutput, torch.Tensor]:
        w = self.cfg.loss
        with self._autocast():
            out = self.model(batch["image"])
        out = out.float()
        with torch.no_grad():
            gt = body_frame_vertices(self.body, batch["pose"], batch["bone"], batch["shape"])
        terms: dict[str, torch.Tensor] = {}
        if w.vertices:
            terms["l3d"] = w.vertices * (out.vertices - gt).abs().sum(-1).mean()
        kp = self.keypoints(out.vertices)
        if w.keypoints_2d:
            kp2d = weak_perspective(kp, out.rotation, out.cam, self.crop)
            terms["proj"] = w.keypoints_2d * L.keypoint_2d_loss(kp2d, batch["keypoints_2d"], self.crop)
        if w.keypoints_3d:
            terms["kp3d"] = w.keypoints_3d * L.keypoint_3d_loss(kp @ out.rotation.transpose(1, 2), batch["keypoints_3d"])
        self._fake_ae = None
        if self.disc is not None:
            self._fake_ae = self._ae_loss(out.vertices).mean()  # L_AE(fake), graph into D and the generator
            if self.cfg.began.weight:
                terms["adv"] = self.cfg.began.weight * self._fake_ae  # Eq. 4.11
        return terms, out, gt

    def training_step(self, batch: dict[str, torch.Tensor], step: int) -> dict[str, float]:
        """One generator update and, with BEGAN, one discriminator update from the same forward
        passes (as BEGAN does: both use the values before either update)."""
        batch = {k: v.to(self.device, non_blocking=True) for k, v in batch.items()}
        self.model.train()
        terms, out, gt = self.losses(batch)
        total = torch.stack(list(terms.values())).sum()
        L.check_finite({**terms, "total": total}, step, batch["key"].cpu())
        gen_params = [p for p in self.model.parameters() if p.requires_grad]
        d_params = [p for p in self.disc.parameters() if p.requires_grad] if self.disc is not None else []
        logs = {k: float(v.detach()) for k, v in terms.items()}
        logs["total"] = float(total.detach())
        self.opt.zero_grad(set_to_none=True)
        total.backward(inputs=gen_params, retain_graph=bool(d_params))
        if self.cfg.optim.grad_clip:
            nn.utils.clip_grad_norm_(gen_params, self.cfg.optim.grad_clip)
        if self.disc is not None:
            b = self.cfg.began
            with torch.set_grad_enabled(bool(d_params)):
                l_real = self._ae_loss(gt).mean()
            l_fake = self._fake_ae
            d_loss = l_real - self.k * l_fake  # Eq. 4.10
            L.check_finite({"disc": d_loss}, step, batch["key"].cpu())
            if self.d_opt is not None:
                self.d_opt.zero_grad(set_to_none=True)
                d_loss.backward(inputs=d_params)
                self.d_opt.step()
            lr_, lf_ = float(l_real.detach()), float(l_fake.detach())
            logs.update(d_real=lr_, d_fake=lf_, convergence=began_convergence(lr_, lf_, b.gamma), k=self.k)
            self.k = began_k_update(self.k, lr_, lf_, b.lambda_k, b.gamma)  # Eq. 4.12
        self.opt.step()
        self.sched.step()
        self._fake_ae = None
        logs["lr"] = float(self.sched.get_last_lr()[0])
        return logs

    @torch.no_grad()
    def predict(self, images: torch.Tensor) -> MeshOutput:
        self.model.eval()
        with self._autocast():
            out = self.model(images.to(self.device))
        return out.float()

    @torch.no_grad()
    def validate(self, loader: Any) -> dict[str, float]:
        """Body-frame errors (mm): ``vertex_mm`` (pelvis-aligned mesh), ``joint_mm`` and ``pa_mpjpe_mm``
        on the evaluation joints through the keypoint regressor (the labels' mesh through the same)."""
        err: dict[str, list[torch.Tensor]] = {"joint_mm": [], "pa_mpjpe_mm": [], "vertex_mm": []}
        for batch in loader:
            batch = {k: v.to(self.device) for k, v in batch.items()}
            out = self.predict(batch["image"])
            gt = body_frame_vertices(self.body, batch["pose"], batch["bone"], batch["shape"])
            pk, gk = self.keypoints(out.vertices)[:, self.eval_idx], self.keypoints(gt)[:, self.eval_idx]
            err["joint_mm"].append(M.mpjpe(pk, gk) * 1000)
            err["pa_mpjpe_mm"].append(M.pa_mpjpe(pk, gk) * 1000)
            pelvis_p = torch.einsum("v,bvc->bc", self.regressor[self.pelvis], out.vertices)[:, None]
            pelvis_g = torch.einsum("v,bvc->bc", self.regressor[self.pelvis], gt)[:, None]
            err["vertex_mm"].append(vertex_error_mm(out.vertices - pelvis_p, gt - pelvis_g))
        return {k: float(torch.cat(v).mean()) for k, v in err.items() if v}


def cam_mean(ds: CropCache, crop: int) -> torch.Tensor:
    """(3,) the mean ``(s, tx, ty)`` of the training caches' labels at the un-augmented crop."""
    return label_cams(ds, crop).mean(0)


def setup(cfg: RecoveryConfig, log: Any = print) -> tuple[MeshTask, CropCache, CropCache | None]:
    """The image-to-mesh task with its model and caches for ``cfg``."""
    set_threads(cfg)
    train, val = open_caches(cfg, log)
    path = model_file(cfg)
    body = blsm.load(path)
    ops, mean, std = mesh_statistics(cfg, body, path, log)
    torch.manual_seed(cfg.train.seed)  # the statistics' draws must not change the initialisation
    task = MeshTask(cfg, body, ops, mean, std, cam_mean(train, cfg.data.crop), train.keypoint_names,
                    checkpoint_meta(cfg, path))
    return task, train, val


SPEC = TaskSpec(name=MeshTask.name, setup=setup, batches=image_batches, best_metric="pa_mpjpe_mm",
                describe=describe_images, distributed=False)
