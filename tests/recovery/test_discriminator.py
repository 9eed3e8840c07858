"""recovery.models.discriminator and the LSGAN losses of recovery.models.losses."""

from __future__ import annotations

import pytest
import torch

from recovery.models import losses as L
from recovery.models.discriminator import PoseDiscriminator, normalise_angles


def test_normalisation_maps_the_limits_to_minus_one_and_one(model):
    lim = model.dof_limits
    lo, hi = lim[:, 0][None], lim[:, 1][None]
    got = normalise_angles(torch.cat([lo, hi, (lo + hi) / 2]), lim)
    torch.testing.assert_close(got, torch.tensor([-1.0, 1.0, 0.0])[:, None].expand(3, 47), atol=1e-6, rtol=0)


def test_output_shape_and_bad_limits(model, gen):
    d = PoseDiscriminator(model.dof_limits, hidden=32)
    assert d(torch.rand(5, 47, generator=gen)).shape == (5,)
    with pytest.raises(ValueError, match=r"limits must be \(D, 2\), got \(47,\)"):
        PoseDiscriminator(model.dof_limits[:, 0])


def test_lsgan_losses_against_hand_values():
    real, fake = torch.tensor([1.0, 0.5, 0.0]), torch.tensor([0.0, 0.5, 2.0])
    # E[(D(real) - 1)^2] + E[D(fake)^2] = (0 + .25 + 1) / 3 + (0 + .25 + 4) / 3
    assert L.lsgan_discriminator_loss(real, fake).item() == pytest.approx(5.5 / 3)
    # E[(D(fake) - 1)^2] = (1 + .25 + 1) / 3
    assert L.lsgan_generator_loss(fake).item() == pytest.approx(2.25 / 3)


def test_keypoint_losses_against_hand_values():
    pred = torch.tensor([[[10.0, 20.0], [0.0, 0.0]]])
    target = torch.tensor([[[12.0, 16.0, 1.0], [50.0, 50.0, 0.0]]])  # the second is invisible
    assert L.keypoint_2d_loss(pred, target, crop=100).item() == pytest.approx((2 + 4) / 100)
    p3, t3 = torch.zeros(1, 2, 3), torch.tensor([[[0.1, -0.2, 0.0], [0.0, 0.0, 0.3]]])
    assert L.keypoint_3d_loss(p3, t3).item() == pytest.approx((0.3 + 0.3) / 2)
    with pytest.raises(FloatingPointError, match=r"non-finite loss kp3d at step 7; batch samples \[3, 4\]"):
        L.check_finite(
            {"kp2d": torch.tensor(1.0), "kp3d": torch.tensor(float("nan"))}, 7, torch.tensor([3, 4])
        )


def test_one_discriminator_step_lowers_its_loss(model, gen):
    torch.manual_seed(0)
    d = PoseDiscriminator(model.dof_limits)
    opt = torch.optim.Adam(d.parameters(), lr=1e-4, weight_decay=1e-4)  # HMR's, the config's defaults
    lo, hi = model.dof_limits[:, 0], model.dof_limits[:, 1]
    real = lo + (hi - lo) * (0.4 + 0.2 * torch.rand(16, 47, generator=gen))  # near the middle of each range
    fake = lo + (hi - lo) * torch.rand(16, 47, generator=gen)  # anywhere
    before = L.lsgan_discriminator_loss(d(real), d(fake))
    opt.zero_grad()
    before.backward()
    opt.step()
    after = L.lsgan_discriminator_loss(d(real), d(fake))
    assert after < before - 1e-3
    for _ in range(20):
        opt.zero_grad()
        loss = L.lsgan_discriminator_loss(d(real), d(fake))
        loss.backward()
        opt.step()
    assert d(real).mean() > d(fake).mean() + 0.5  # it tells them apart
