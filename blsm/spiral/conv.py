"""Spiral convolution and mesh pooling (thesis Eqs. 4.2-4.4, Sec. 4.3.2; Neural3DMM, spiralnet++).

The operators (spiral indices, ``Q^d``, ``Q^u``) are precomputed once (:mod:`blsm.spiral.hierarchy`);
the modules only hold them as buffers and apply them.

Layout: the modules take **vertex-major** features ``(N, B, C)``. Gathering a vertex's neighbours
then copies contiguous ``B x C`` blocks instead of ``C`` floats, which on a CPU is what a spiral
network's time goes to (docs/benchmarks.md); :func:`spiral_gather` is the batch-major reference.
"""

from __future__ import annotations

import torch
from torch import nn


def spiral_gather(x: torch.Tensor, indices: torch.Tensor) -> torch.Tensor:
    """Features along every vertex's spiral, concatenated (Eq. 4.4 before the weights); reference.

    Args:
        x: (B, N, C) vertex features (batch-major).
        indices: (N, L) spiral indices; -1 pads (reads a zero feature).

    Returns:
        (B, N, L * C): row n holds ``x[S_1(n)], ..., x[S_L(n)]``.
    """
    b, n, c = x.shape
    padded = torch.cat([x, x.new_zeros(b, 1, c)], dim=1)  # (B, N + 1, C)
    idx = torch.where(indices < 0, torch.full_like(indices, n), indices)
    return padded[:, idx.reshape(-1)].reshape(b, n, -1)


def spiral_conv(x: torch.Tensor, indices: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """``(f * g)_x = sum_l g_l f(S_l(x)) + b`` (Eq. 4.4) on vertex-major features.

    Args:
        x: (N, B, C_in). indices: (N, L), -1 pads.
        weight: (C_out, L * C_in), ``nn.Linear``'s layout over :func:`spiral_gather`'s rows.
        bias: (C_out,) or None.

    Returns:
        (N, B, C_out).
    """
    n, b, c = x.shape
    length = indices.shape[1]
    padded = torch.cat([x, x.new_zeros(1, b, c)], dim=0)  # (N + 1, B, C)
    idx = torch.where(indices < 0, torch.full_like(indices, n), indices)
    w = weight.reshape(weight.shape[0], length, c).permute(1, 2, 0)  # (L, C_in, C_out)
    out = None
    for k in range(length):
        term = torch.index_select(padded, 0, idx[:, k]) @ w[k]  # (N, B, C_out)
        out = term if out is None else out + term
    return out if bias is None else out + bias


class SpiralConv(nn.Module):
    """Eq. 4.4 as a module: ``(N, B, C_in) -> (N, B, C_out)`` over fixed spiral ``indices`` (N, L)."""

    def __init__(self, in_channels: int, out_channels: int, indices: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("indices", indices.long())  # (N, L)
        self.linear = nn.Linear(in_channels * indices.shape[1], out_channels)
        nn.init.xavier_uniform_(self.linear.weight)
        nn.init.zeros_(self.linear.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return spiral_conv(x, self.indices, self.linear.weight, self.linear.bias)


class Pool(nn.Module):
    """Down-sampling by ``Q^d``: keep the surviving vertices, (n, B, C) -> (m, B, C)."""

    def __init__(self, down: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("down", down.long())  # (m,)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.index_select(x, 0, self.down)


class Unpool(nn.Module):
    """Up-sampling by ``Q^u``: barycentric interpolation, (m, B, C) -> (n, B, C)."""

    def __init__(self, up_index: torch.Tensor, up_weight: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("up_index", up_index.long())  # (n, 3)
        self.register_buffer("up_weight", up_weight.float())  # (n, 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        w = self.up_weight.to(x.dtype)
        out = None
        for k in range(3):
            term = torch.index_select(x, 0, self.up_index[:, k]) * w[:, k, None, None]
            out = term if out is None else out + term
        return out
