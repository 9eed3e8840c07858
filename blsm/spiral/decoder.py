"""The spiral mesh decoder (thesis Sec. 4.3.3 / Table 4.1's second half) and the per-vertex normaliser.

:class:`SpiralDecoder`: a fully connected layer from the latent code to the coarsest mesh, then one
block per level of un-pooling (``Q^u``) and a spiral convolution (Eq. 9 / thesis Eq. 4.4), ELU after
each, and an output spiral convolution to 3 channels. ``recovery``'s autoencoder and image-to-mesh
network use it on normalised vertices; :mod:`blsm.spiral.shape` uses it on normalised T-pose
residuals (BLSM-spiral, Eq. 11).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from blsm.spiral.conv import SpiralConv, Unpool
from blsm.spiral.hierarchy import MeshOperators


class MeshNormalizer(nn.Module):
    """``(V - mean) / std`` per vertex and coordinate (buffers; std floored at ``eps`` metres)."""

    def __init__(self, mean: torch.Tensor, std: torch.Tensor, eps: float = 1e-4) -> None:
        super().__init__()
        self.register_buffer("mean", mean.float().clone())  # (V, 3)
        self.register_buffer("std", std.float().clamp(min=eps))  # (V, 3)

    def forward(self, v: torch.Tensor) -> torch.Tensor:
        return (v - self.mean) / self.std

    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.std + self.mean


class SpiralDecoder(nn.Module):
    """(B, latent) -> (B, V, 3) normalised vertices (the mirror of ``recovery.models.mesh_ae.SpiralEncoder``)."""

    def __init__(self, ops: MeshOperators, channels: Sequence[int] = (16, 32, 64, 128), latent: int = 128) -> None:
        super().__init__()
        if len(channels) != len(ops.levels):
            raise ValueError(f"{len(channels)} channel widths for {len(ops.levels)} mesh levels")
        self.coarse, self.width = ops.sizes[-1], channels[-1]
        self.fc = nn.Linear(latent, self.coarse * self.width)
        self.unpools = nn.ModuleList()
        self.convs = nn.ModuleList()
        for i in reversed(range(len(channels))):
            lv = ops.levels[i]
            self.unpools.append(Unpool(torch.as_tensor(lv.up_index), torch.as_tensor(lv.up_weight)))
            self.convs.append(SpiralConv(channels[i], channels[i - 1] if i > 0 else channels[0], torch.as_tensor(ops.spirals[i])))
        self.conv_out = SpiralConv(channels[0], 3, torch.as_tensor(ops.spirals[0]))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = self.fc(z).reshape(z.shape[0], self.coarse, self.width).transpose(0, 1)  # (n, B, C)
        for unpool, conv in zip(self.unpools, self.convs):
            x = F.elu(conv(unpool(x)))
        return self.conv_out(x).transpose(0, 1)  # (B, V, 3)
