"""Learning BLSM-spiral's decoder as an auto-decoder (paper 000 Eq. 17, thesis Eq. 5.29; DeepSDF, Park et al. 2019).

There is no encoder: every training body n gets its own latent code z^n, and the decoder D and the
codes are optimised together,

    argmin_{D, z}  sum_n mean_i || V_D^n,i - D(z^n)_i ||  +  code_prior * ||z^n||^2,

on the T-pose residuals V_D^n of the linear shape space (:mod:`blsm.learn.training.train` step 4: the
rest-pose registrations un-skinned, minus the mean template and the bone correctives). The data term
is Eq. 17's per-vertex Euclidean distance (in mm, averaged over vertices); the code prior is
DeepSDF's zero-mean Gaussian on the codes, which keeps the latent space compact so that a code can be
searched for a new body (:func:`fit_codes`; the staged fit of :mod:`blsm.learn.evaluation.fit` does the same
with pose and bones free). Optimiser as in the paper (Sec. 5): Adam, learning rate 1e-3 and weight
decay 5e-5 for the network, 0.1 and 1e-7 for the codes (DeepSDF's initial codes: N(0, 0.01^2)), both
rates x0.99 after each epoch.

The network (:class:`blsm.spiral.shape.SpiralShapeDecoder`) is the spiral decoder of
:mod:`blsm.spiral.decoder` with widths ``channels`` fine to coarse (default (16, 32, 32, 48): the
paper's (48, 32, 32, 16) read from the coarse end) on the hierarchy of down-sampling factors
(4, 2, 2, 2) (the paper's up-sampling factors (2, 2, 2, 4)). Differences from the paper: no batch
normalisation (a code is fitted one body at a time, where batch statistics do not exist), and the
decoder's order of un-pooling before convolution is the thesis' (Table 4.1).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from typing import Any

import torch

from blsm.spiral.hierarchy import MeshOperators, MeshOpsSettings
from blsm.spiral.shape import SpiralShapeDecoder


@dataclass
class SpiralConfig:
    """The ``train.shape.spiral`` section: BLSM-spiral's network and its training.

    Attributes:
        latent: L, the size of the latent code (the number of shape coefficients).
        channels: spiral-convolution widths per level, fine to coarse.
        factors, rings, lengths: the hierarchy (:class:`blsm.spiral.hierarchy.MeshOpsSettings`).
        epochs: passes over the training bodies.
        batch_size: bodies per step.
        lr, weight_decay: Adam on the network (paper: 1e-3, 5e-5).
        code_lr, code_weight_decay: Adam on the codes (paper: 0.1, 1e-7).
        lr_decay: both learning rates are multiplied by this after each epoch (paper: 0.99).
        code_prior: weight of ``||z||^2`` against the data term in mm (DeepSDF's code regulariser).
        code_init_std: standard deviation of the initial codes (DeepSDF: 0.01).
        seed: the initial network and codes.
    """

    latent: int = 16
    channels: tuple[int, ...] = (16, 32, 32, 48)
    factors: tuple[float, ...] = (4, 2, 2, 2)
    rings: tuple[int, ...] = (2, 1, 1, 1)
    lengths: tuple[int, ...] = (25, 9, 9, 9)
    epochs: int = 300
    batch_size: int = 16
    lr: float = 1e-3
    weight_decay: float = 5e-5
    code_lr: float = 0.1
    code_weight_decay: float = 1e-7
    lr_decay: float = 0.99
    code_prior: float = 1e-2
    code_init_std: float = 0.01
    seed: int = 0

    def __post_init__(self) -> None:
        if self.latent < 1 or self.epochs < 1 or self.batch_size < 1:
            raise ValueError("shape.spiral: latent, epochs and batch_size must be >= 1")
        if len(self.channels) != len(self.factors) or min(self.channels, default=0) < 1:
            raise ValueError(f"shape.spiral.channels needs one width >= 1 per level ({len(self.factors)}), "
                             f"got {list(self.channels)}")
        if self.lr <= 0 or self.code_lr <= 0 or not 0 < self.lr_decay <= 1:
            raise ValueError("shape.spiral: lr and code_lr must be > 0 and lr_decay in (0, 1]")
        if min(self.weight_decay, self.code_weight_decay, self.code_prior, self.code_init_std) < 0:
            raise ValueError("shape.spiral: weight decays, code_prior and code_init_std must be >= 0")
        self.settings()  # factors, rings and lengths checked there

    def settings(self) -> MeshOpsSettings:
        """The hierarchy's settings."""
        return MeshOpsSettings(factors=self.factors, rings=self.rings, lengths=self.lengths)


def _log(msg: str) -> None:
    print(f"[spiral] {msg}", file=sys.stderr, flush=True)


def vertex_error_mm(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,) mean per-vertex Euclidean distance in mm of (B, V, 3) metres."""
    return (pred - target).norm(dim=-1).mean(-1) * 1000.0


def train_auto_decoder(residuals: torch.Tensor, ops: MeshOperators, cfg: SpiralConfig,
                       log_every: int = 50) -> tuple[SpiralShapeDecoder, torch.Tensor, dict[str, Any]]:
    """Learn D and the codes of Eq. 17 (module docstring).

    Args:
        residuals: (N, V, 3) T-pose residuals V_D^n, metres (any device; training runs there).
        ops: the template's hierarchy.
        cfg: :class:`SpiralConfig`.
        log_every: epochs between log lines (0: none).

    Returns:
        The decoder (float32, on the residuals' device, eval mode), the codes (N, L) and a report:
        the final training error in mm with the learnt codes, the loss curve, the seconds.
    """
    if residuals.dim() != 3 or residuals.shape[2] != 3 or residuals.shape[0] < 1:
        raise ValueError(f"residuals must be (N, V, 3) with N >= 1, got {tuple(residuals.shape)}")
    device = residuals.device
    target = residuals.detach().float()
    n = target.shape[0]
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    std = target.std(0) if n > 1 else torch.ones_like(target[0]) * 1e-3
    dec = SpiralShapeDecoder(ops, cfg.latent, cfg.channels, target.mean(0), std).to(device)
    codes = (torch.randn(n, cfg.latent, generator=gen) * cfg.code_init_std).to(device).requires_grad_(True)
    opt = torch.optim.Adam([
        {"params": list(dec.parameters()), "lr": cfg.lr, "weight_decay": cfg.weight_decay},
        {"params": [codes], "lr": cfg.code_lr, "weight_decay": cfg.code_weight_decay},
    ])
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, cfg.lr_decay)
    curve: list[float] = []
    t0 = time.perf_counter()
    for epoch in range(cfg.epochs):
        order = torch.randperm(n, generator=gen).to(device)
        total = 0.0
        for s in range(0, n, cfg.batch_size):
            idx = order[s : s + cfg.batch_size]
            data = vertex_error_mm(dec(codes[idx]), target[idx]).mean()
            loss = data + cfg.code_prior * codes[idx].pow(2).sum(1).mean()
            if not torch.isfinite(loss):
                raise FloatingPointError(f"auto-decoder: non-finite loss at epoch {epoch}")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += float(data.detach()) * len(idx)
        sched.step()
        curve.append(total / n)
        if log_every and (epoch % log_every == 0 or epoch == cfg.epochs - 1):
            _log(f"epoch {epoch}: training error {curve[-1]:.3f} mm")
    dec.eval()
    codes = codes.detach()
    with torch.no_grad():
        err = torch.cat([vertex_error_mm(dec(codes[s : s + 64]), target[s : s + 64]) for s in range(0, n, 64)])
    report = {"latent": cfg.latent, "bodies": n, "train_error_mm": float(err.mean()),
              "loss_curve_mm": [round(c, 4) for c in curve[:: max(1, len(curve) // 50)]],
              "code_norm_mean": float(codes.norm(dim=1).mean()), "seconds": round(time.perf_counter() - t0, 1)}
    return dec, codes, report


def fit_codes(dec: SpiralShapeDecoder, residuals: torch.Tensor, steps: int = 300, lr: float = 0.05,
              code_prior: float = 0.0, init: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The codes of new residuals with D fixed (the shape space alone, no pose): Adam on z.

    Args:
        dec: a trained decoder. residuals: (B, V, 3) metres.
        steps, lr: Adam. code_prior: weight of ``||z||^2`` (as in training).
        init: (B, L) starting codes (default zeros).

    Returns:
        codes (B, L) and the (B,) errors in mm.
    """
    target = residuals.detach().to(dec.normalizer.mean.dtype)
    z = (torch.zeros(target.shape[0], dec.latent, dtype=target.dtype, device=target.device)
         if init is None else init.detach().clone().to(target)).requires_grad_(True)
    opt = torch.optim.Adam([z], lr=lr)
    for p in dec.parameters():
        p.requires_grad_(False)
    try:
        for _ in range(steps):
            loss = vertex_error_mm(dec(z), target).sum() + code_prior * z.pow(2).sum()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
    finally:
        for p in dec.parameters():
            p.requires_grad_(True)
    with torch.no_grad():
        return z.detach(), vertex_error_mm(dec(z), target)
