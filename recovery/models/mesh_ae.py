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

from blsm.spiral.conv import Pool, SpiralConv
from blsm.spiral.decoder import MeshNormalizer, SpiralDecoder
from blsm.spiral.hierarchy import MeshOperators


class SpiralEncoder(nn.Module):
    """(B, V, 3) normalised vertices -> (B, latent) (vertex-major inside, :mod:`blsm.spiral.conv`)."""

    def __init__(self, ops: MeshOperators, channels: Sequence[int] = (16, 32, 64, 128), latent: int = 128) -> None:
        super().__init__()
        if len(channels) != len(ops.levels):
            raise ValueError(f"{len(channels)} channel widths for {len(ops.levels)} mesh levels")
        self.conv_in = SpiralConv(3, channels[0], torch.as_tensor(ops.spirals[0]))
        self.convs = nn.ModuleList()
        self.pools = nn.ModuleList()
        prev = channels[0]
        for i, c in enumerate(channels):
            self.convs.append(SpiralConv(prev, c, torch.as_tensor(ops.spirals[i])))
            self.pools.append(Pool(torch.as_tensor(ops.levels[i].down)))
            prev = c
        self.fc = nn.Linear(ops.sizes[-1] * channels[-1], latent)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.elu(self.conv_in(x.transpose(0, 1)))  # (V, B, C)
        for conv, pool in zip(self.convs, self.pools):
            x = pool(F.elu(conv(x)))
        return self.fc(x.transpose(0, 1).flatten(1))


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
