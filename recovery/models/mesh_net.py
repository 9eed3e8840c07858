"""The image-to-mesh network of thesis Fig. 4.4 / Sec. 4.5.1.

Backbone features -> two FC layers (ReLU) -> the 1024-D image feature; from it

- the **latent code regressor**: one FC layer to the 128-D code, decoded into the body-frame
  vertices by the spiral decoder (:class:`blsm.spiral.decoder.SpiralDecoder`) and the
  training meshes' normalisation;
- the **camera branch**: one FC layer to 7 values, a quaternion ``(w, x, y, z)`` rotating the body
  frame into the camera frame and the weak-perspective ``(s, tx, ty)`` of :mod:`recovery.utils.geometry`
  (``tx, ty``: where the pelvis projects, crop coordinates in [-1, 1]; ``s``: the scale, pelvis depth
  ``2 f / (S s)``). Its bias starts at the training set's mean camera and a rotation upright and
  facing the camera.

Projection (Eq. 4.8's Pi): weak perspective, ``u = S / 2 (1 + tx + s (R v)_x)`` and likewise v, for
points ``v`` relative to the pelvis. For overlays and segmentation the same camera is turned into a
camera-frame translation with ``K_crop`` (:func:`recovery.utils.geometry.cam_to_translation`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion
from torch import nn

from blsm.spiral.decoder import MeshNormalizer, SpiralDecoder
from blsm.spiral.hierarchy import MeshOperators
from recovery.models.backbones import build_backbone
from recovery.utils.geometry import UPRIGHT_FACING_CAMERA


@dataclass
class MeshOutput:
    """The network's prediction.

    Attributes:
        vertices: (B, V, 3) body frame (no global rotation), metres, as decoded (pelvis near 0).
        rotation: (B, 3, 3) body frame -> camera frame.
        cam: (B, 3) ``(s, tx, ty)``.
        latent: (B, latent) the code.
    """

    vertices: torch.Tensor
    rotation: torch.Tensor
    cam: torch.Tensor
    latent: torch.Tensor

    def float(self) -> MeshOutput:
        return MeshOutput(**{k: v.float() for k, v in vars(self).items()})


def weak_perspective(points: torch.Tensor, rotation: torch.Tensor, cam: torch.Tensor, crop: int) -> torch.Tensor:
    """Eq. 4.8's Pi: (B, K, 3) pelvis-relative body-frame points -> (B, K, 2) crop pixels."""
    p = points @ rotation.transpose(1, 2)  # (B, K, 3) camera-frame orientation
    norm = cam[:, None, 0:1] * p[..., :2] + cam[:, None, 1:3]
    return crop / 2 * (1 + norm)


class MeshRegressor(nn.Module):
    """Backbone + FC + spiral decoder + camera branch (module docstring).

    Args:
        backbone: a name of :func:`recovery.models.backbones.build_backbone`.
        ops: the template's mesh operators.
        mean, std: (V, 3) the training meshes' normalisation.
        cam_init: (3,) the mean ``(s, tx, ty)`` of the training crops.
        pretrained: load the backbone's ImageNet weights.
        channels, latent, hidden: the decoder (Table 4.1) and the FC width (1024).
    """

    def __init__(self, backbone: str, ops: MeshOperators, mean: torch.Tensor, std: torch.Tensor,
                 cam_init: torch.Tensor, pretrained: bool = False, channels: tuple[int, ...] = (16, 32, 64, 128),
                 latent: int = 128, hidden: int = 1024) -> None:
        super().__init__()
        self.backbone = build_backbone(backbone, pretrained=pretrained)
        self.fc = nn.Sequential(nn.Linear(self.backbone.out_channels, hidden), nn.ReLU(inplace=True),
                                nn.Linear(hidden, hidden), nn.ReLU(inplace=True))
        self.to_latent = nn.Linear(hidden, latent)
        self.to_camera = nn.Linear(hidden, 7)
        self.decoder = SpiralDecoder(ops, channels, latent)
        self.normalizer = MeshNormalizer(mean, std)
        nn.init.xavier_uniform_(self.to_camera.weight, gain=0.01)
        q0 = rotation_matrix_to_quaternion(UPRIGHT_FACING_CAMERA[None])[0]  # upright, facing the camera
        with torch.no_grad():
            self.to_camera.bias.copy_(torch.cat([q0, cam_init.float()]))

    def forward(self, images: torch.Tensor) -> MeshOutput:
        """Args: images (B, 3, H, W) RGB in [0, 1]."""
        phi = self.fc(self.backbone(self.backbone.normalize(images)))
        z = self.to_latent(phi)
        verts = self.normalizer.inverse(self.decoder(z))
        c = self.to_camera(phi)
        q = c[:, :4] / c[:, :4].norm(dim=-1, keepdim=True).clamp(min=1e-8)
        return MeshOutput(vertices=verts, rotation=quaternion_to_rotation_matrix(q), cam=c[:, 4:], latent=z)
