"""The 47-D pose discriminator of HMR-BLSM (thesis Sec. 6.4.3).

HMR judges SMPL poses with per-joint discriminators and a pose embedding; every BLSM atom is limited
by construction (Eq. 6), so one network suffices: two fully connected layers of 1024 units that take
the 47 pose values and output one value. The input is each atom's angle normalised by its range,
``2 (a - lo) / (hi - lo) - 1`` in [-1, 1], so that no atom dominates by the width of its range.
Trained with the least-squares GAN losses of HMR (:mod:`recovery.models.losses`).
"""

from __future__ import annotations

import torch
from torch import nn


def normalise_angles(angles: torch.Tensor, limits: torch.Tensor) -> torch.Tensor:
    """(B, 47) radians -> (B, 47) in [-1, 1] for angles inside ``limits`` (47, 2) = (lo, hi)."""
    lo, hi = limits[:, 0], limits[:, 1]
    return 2.0 * (angles - lo) / (hi - lo) - 1.0


class PoseDiscriminator(nn.Module):
    """FC 1024 -> ReLU -> FC 1024 -> ReLU -> 1 on the range-normalised 47 angles.

    Args:
        limits: (47, 2) the model's ``dof_limits`` (radians).
        hidden: width of the two layers (thesis: 1024).
    """

    def __init__(self, limits: torch.Tensor, hidden: int = 1024) -> None:
        super().__init__()
        if limits.dim() != 2 or limits.shape[1] != 2:
            raise ValueError(f"limits must be (D, 2), got {tuple(limits.shape)}")
        self.register_buffer("limits", limits.clone().float(), persistent=False)
        self.net = nn.Sequential(
            nn.Linear(limits.shape[0], hidden), nn.ReLU(inplace=True),
            nn.Linear(hidden, hidden), nn.ReLU(inplace=True),
            nn.Linear(hidden, 1),
        )

    def forward(self, angles: torch.Tensor) -> torch.Tensor:
        """(B, 47) radians -> (B,) scores (real near 1, fake near 0 under the LSGAN losses)."""
        return self.net(normalise_angles(angles, self.limits.to(angles.dtype)))[:, 0]
