"""HMR's regression head (Kanazawa et al. 2018): iterative error feedback on the parameter vector
``Theta``, its layout and its starting point ``Theta_0``.

``Theta`` is laid out by :class:`ParamLayout`:

- ``pose``: the 47 unconstrained values x of the atoms (the BLSM model applies Eq. 6, so every
  predicted angle lies inside its limits by construction);
- ``orient``: the global orientation in the camera frame as the continuous 6-D rotation;
- ``bone``: all the model's bone coefficients (Eqs. 4-5);
- ``shape``: the leading ``num_shape`` shape coefficients (Eq. 8; the rest are 0);
- ``cam``: ``(s, tx, ty)`` of :mod:`recovery.utils.geometry`, turned into the pelvis' camera-frame
  translation with the crop's ``K_crop``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from recovery.utils.geometry import UPRIGHT_FACING_CAMERA, matrix_to_rot6d


@dataclass(frozen=True)
class ParamLayout:
    """Slices of the parameter vector ``Theta`` (module docstring)."""

    num_dofs: int
    num_bone: int
    num_shape: int

    @property
    def size(self) -> int:
        return self.num_dofs + 6 + self.num_bone + self.num_shape + 3

    def slices(self) -> dict[str, slice]:
        n, out = 0, {}
        for name, width in (("pose", self.num_dofs), ("orient", 6), ("bone", self.num_bone), ("shape", self.num_shape), ("cam", 3)):
            out[name] = slice(n, n + width)
            n += width
        return out

    def split(self, theta: torch.Tensor) -> dict[str, torch.Tensor]:
        return {k: theta[..., s] for k, s in self.slices().items()}

    def join(self, pose: torch.Tensor, orient_6d: torch.Tensor, bone: torch.Tensor, shape: torch.Tensor,
             cam: torch.Tensor) -> torch.Tensor:
        return torch.cat([pose, orient_6d, bone, shape[..., : self.num_shape], cam], dim=-1)


class IEFRegressor(nn.Module):
    """Iterative error feedback (HMR Sec. 3.1): ``Theta_{t+1} = Theta_t + D([phi, Theta_t])``."""

    def __init__(self, in_features: int, init: torch.Tensor, hidden: int = 1024, dropout: float = 0.5,
                 iterations: int = 3) -> None:
        super().__init__()
        size = int(init.shape[0])
        self.iterations = int(iterations)
        self.register_buffer("init", init.clone().float())  # (P,) Theta_0: the training set's means
        self.fc1 = nn.Linear(in_features + size, hidden)
        self.fc2 = nn.Linear(hidden, hidden)
        self.drop1, self.drop2 = nn.Dropout(dropout), nn.Dropout(dropout)
        self.dec = nn.Linear(hidden, size)
        nn.init.xavier_uniform_(self.dec.weight, gain=0.01)  # SPIN: start near Theta_0
        nn.init.zeros_(self.dec.bias)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """(B, C) -> (T + 1, B, P): Theta_0 and every iteration's estimate."""
        theta = self.init.to(features.dtype).expand(features.shape[0], -1)
        out = [theta]
        for _ in range(self.iterations):
            x = torch.cat([features, theta], dim=-1)
            x = self.drop1(torch.relu(self.fc1(x)))
            x = self.drop2(torch.relu(self.fc2(x)))
            theta = theta + self.dec(x)
            out.append(theta)
        return torch.stack(out)


def mean_theta(layout: ParamLayout, pose: torch.Tensor, bone: torch.Tensor, shape: torch.Tensor,
               cam: torch.Tensor, orient: torch.Tensor = UPRIGHT_FACING_CAMERA) -> torch.Tensor:
    """``Theta_0`` from training labels: the mean x, bone, shape and camera, and ``orient``.

    The orientation is not averaged: with cameras all around the people (yaw uniform over 360
    degrees) the mean rotation matrix is degenerate, so Theta_0 is upright and facing the camera.

    Args:
        pose (N, 47), bone (N, Kb), shape (N, >= num_shape), cam (N, 3); orient (3, 3).
    """
    return layout.join(pose.double().mean(0), matrix_to_rot6d(orient.double()[None])[0], bone.double().mean(0),
                       shape.double().mean(0), cam.double().mean(0)).float()
