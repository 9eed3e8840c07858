"""blsm.spiral.conv: Eq. 4.4's convolution on the spirals of blsm.spiral.sequences."""

from __future__ import annotations

import torch
from recovery_helpers import sphere

from blsm.spiral.conv import SpiralConv, spiral_conv, spiral_gather
from blsm.spiral.sequences import spiral_sequences


def test_spiral_conv_matches_the_gathered_reference_and_pads_with_zeros():
    torch.manual_seed(0)
    v, f = sphere(1)
    idx = torch.as_tensor(spiral_sequences(v, f, rings=2, length=20))
    assert (idx < 0).any()  # some spirals are padded
    conv = SpiralConv(5, 7, idx)
    x = torch.randn(3, len(v), 5)  # (B, N, C)
    want = torch.nn.functional.linear(spiral_gather(x, idx), conv.linear.weight, conv.linear.bias)
    got = conv(x.transpose(0, 1)).transpose(0, 1)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    # a padded slot reads zero: its weights do not matter
    w = conv.linear.weight.detach().clone().reshape(7, 20, 5)
    row = int((idx < 0).any(1).nonzero()[0])
    slot = int((idx[row] < 0).nonzero()[0])
    w[:, slot] = 100.0
    got2 = spiral_conv(x.transpose(0, 1), idx, w.reshape(7, -1), conv.linear.bias)
    torch.testing.assert_close(got2[row], got[:, row], rtol=1e-5, atol=1e-5)


def test_spiral_conv_gradcheck():
    v, f = sphere(0)
    idx = torch.as_tensor(spiral_sequences(v, f, rings=1, length=7))
    x = torch.randn(len(v), 2, 3, dtype=torch.float64, requires_grad=True)
    w = torch.randn(4, 7 * 3, dtype=torch.float64, requires_grad=True)
    b = torch.randn(4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x, w, b: spiral_conv(x, idx, w, b), (x, w, b))
