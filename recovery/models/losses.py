"""Losses of the recovery networks: pure functions, each (B, ...) -> a scalar mean.

Weights live in :class:`recovery.config.LossConfig`; the forms follow HMR / SPIN / HMR 2.0:
visibility-weighted L1 on normalised 2D keypoints, pelvis-aligned L1 on 3D keypoints, MSE on
parameters, least-squares GAN terms for the discriminator (HMR Eq. 6 and its generator term).
"""

from __future__ import annotations

import torch


def keypoint_2d_loss(pred: torch.Tensor, target: torch.Tensor, crop: int,
                     normaliser: torch.Tensor | None = None) -> torch.Tensor:
    """L1 between 2D keypoints in crop coordinates normalised to [-0.5, 0.5], weighted by visibility.

    Args:
        pred: (B, K, 2) pixels. target: (B, K, 3) pixels and visibility (0 / 1).
        crop: crop side in pixels.
        normaliser: () what the sum is divided by; default the number of visible keypoints (at
            least 1). One process' share of the loss over several processes' batches passes
            :func:`recovery.distributed.share_normaliser` of its visible count.

    Returns:
        sum over visible keypoints of the L1 distance, divided by the number of visible keypoints
        (0 when none is visible).
    """
    w = target[..., 2]
    err = ((pred - target[..., :2]) / crop).abs().sum(-1)  # (B, K)
    return (err * w).sum() / (w.sum().clamp(min=1.0) if normaliser is None else normaliser)


def keypoint_3d_loss(pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """L1 (metres) between pelvis-relative 3D keypoints (B, K, 3), mean over keypoints and batch."""
    err = (pred - target).abs().sum(-1)  # (B, K)
    if weights is None:
        return err.mean()
    return (err * weights).sum() / weights.sum().clamp(min=1.0)


def mse(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared error over every element."""
    return (pred - target).square().mean()


def lsgan_discriminator_loss(real: torch.Tensor, fake: torch.Tensor) -> torch.Tensor:
    """HMR Eq. 6: ``E[(D(real) - 1)^2] + E[D(fake)^2]``."""
    return (real - 1.0).square().mean() + fake.square().mean()


def lsgan_generator_loss(fake: torch.Tensor) -> torch.Tensor:
    """HMR's adversarial term of the generator: ``E[(D(fake) - 1)^2]``."""
    return (fake - 1.0).square().mean()


def check_finite(losses: dict[str, torch.Tensor], step: int, indices: torch.Tensor | None) -> None:
    """Raise ``FloatingPointError`` naming the step, the term and the batch's sample indices when a
    loss is NaN or infinite (training must stop, not continue on garbage)."""
    bad = [k for k, v in losses.items() if not torch.isfinite(v).all()]
    if bad:
        idx = [] if indices is None else indices.tolist()
        raise FloatingPointError(f"non-finite loss {', '.join(bad)} at step {step}; batch samples {idx}")
