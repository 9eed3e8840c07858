"""The mesh convolutional autoencoder of thesis Sec. 4.3.3 / Table 4.1 and its halves.

Encoder: a spiral convolution (3 -> 16, kernel 2) on the template, then four blocks of a spiral
convolution and a pooling, channels (16, 32, 64, 128), kernels (2, 1, 1, 1), vertex reduction
(4, 2, 2, 2), then a fully connected layer to the 128-D latent code. The decoder mirrors it: a
fully connected layer to the coarsest mesh, four blocks of un-pooling and a spiral convolution
(128 -> 64 -> 32 -> 16 -> 16), and an output spiral convolution (16 -> 3, kernel 2). ELU (with the
convolutions' biases) after every convolution but the output.

Inputs are normalised per vertex and coordinate by the training meshes' mean and standard
deviation (:class:`MeshNormalizer`); the autoencoder's loss is L1 on the normalised vertices
(Eq. 4.5).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from recovery.mesh.operators import MeshOperators
from recovery.models.spiral_conv import Pool, SpiralConv, Unpool


def _t(a) -> torch.Tensor:  # noqa: ANN001 - numpy array
    return torch.as_tensor(a)


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


class SpiralEncoder(nn.Module):
    """(B, V, 3) normalised vertices -> (B, latent) (vertex-major inside, :mod:`recovery.models.spiral_conv`)."""

    def __init__(self, ops: MeshOperators, channels: Sequence[int] = (16, 32, 64, 128), latent: int = 128) -> None:
        super().__init__()
        if len(channels) != len(ops.levels):
            raise ValueError(f"{len(channels)} channel widths for {len(ops.levels)} mesh levels")
        self.conv_in = SpiralConv(3, channels[0], _t(ops.spirals[0]))
        self.convs = nn.ModuleList()
        self.pools = nn.ModuleList()
        prev = channels[0]
        for i, c in enumerate(channels):
            self.convs.append(SpiralConv(prev, c, _t(ops.spirals[i])))
            self.pools.append(Pool(_t(ops.levels[i].down)))
            prev = c
        self.fc = nn.Linear(ops.sizes[-1] * channels[-1], latent)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.elu(self.conv_in(x.transpose(0, 1)))  # (V, B, C)
        for conv, pool in zip(self.convs, self.pools):
            x = pool(F.elu(conv(x)))
        return self.fc(x.transpose(0, 1).flatten(1))


class SpiralDecoder(nn.Module):
    """(B, latent) -> (B, V, 3) normalised vertices (the mirror of :class:`SpiralEncoder`)."""

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
            self.unpools.append(Unpool(_t(lv.up_index), _t(lv.up_weight)))
            self.convs.append(SpiralConv(channels[i], channels[i - 1] if i > 0 else channels[0], _t(ops.spirals[i])))
        self.conv_out = SpiralConv(channels[0], 3, _t(ops.spirals[0]))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = self.fc(z).reshape(z.shape[0], self.coarse, self.width).transpose(0, 1)  # (n, B, C)
        for unpool, conv in zip(self.unpools, self.convs):
            x = F.elu(conv(unpool(x)))
        return self.conv_out(x).transpose(0, 1)  # (B, V, 3)


class MeshAutoencoder(nn.Module):
    """Normaliser + :class:`SpiralEncoder` + :class:`SpiralDecoder` (Table 4.1).

    ``forward`` works on normalised vertices (the space of Eq. 4.5); :meth:`reconstruct` on metres.
    """

    def __init__(self, ops: MeshOperators, mean: torch.Tensor, std: torch.Tensor,
                 channels: Sequence[int] = (16, 32, 64, 128), latent: int = 128) -> None:
        super().__init__()
        self.normalizer = MeshNormalizer(mean, std)
        self.encoder = SpiralEncoder(ops, channels, latent)
        self.decoder = SpiralDecoder(ops, channels, latent)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) normalised -> (B, V, 3) normalised reconstruction."""
        return self.decoder(self.encoder(x))

    def reconstruct(self, v: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) metres -> (B, V, 3) metres."""
        return self.normalizer.inverse(self(self.normalizer(v)))
