"""HMR-BLSM: HMR's regressor (Kanazawa et al. 2018) with its SMPL head replaced by BLSM (thesis
Sec. 6.4.3).

Pooled backbone features -> iterative error feedback: starting from the mean parameters ``Theta_0``,
each of ``ief_iterations`` steps regresses a correction from ``[features, Theta_t]`` through two FC
layers of ``hidden`` units with ReLU and dropout, ``Theta_{t+1} = Theta_t + dTheta``. ``Theta`` is
laid out by :class:`ParamLayout`:

- ``pose``: the 47 unconstrained values x of the atoms (the BLSM model applies Eq. 6, so every
  predicted angle lies inside its limits by construction);
- ``orient``: the global orientation in the camera frame as the continuous 6-D rotation;
- ``bone``: all the model's bone coefficients (Eqs. 4-5);
- ``shape``: the leading ``num_shape`` shape coefficients (Eq. 8; the rest are 0);
- ``cam``: ``(s, tx, ty)`` of :mod:`recovery.geometry`, turned into the pelvis' camera-frame
  translation with the crop's ``K_crop``.

:func:`body_outputs` runs BLSM on the prediction: keypoints and vertices relative to the pelvis in
the camera frame, the translation, and the 2D keypoints projected with ``K_crop``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from recovery.geometry import cam_to_translation, matrix_to_rot6d, project, rot6d_to_matrix
from recovery.models.backbone import build_backbone


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


@dataclass
class HMROutput:
    """The regressor's prediction (the last IEF iteration) and every iteration's parameters.

    Attributes:
        pose: (B, 47) unconstrained atom values x.
        orient: (B, 3, 3) global orientation, camera frame.
        bone: (B, Kb) bone coefficients.
        shape: (B, Ks) shape coefficients of the model (zeros beyond ``num_shape``).
        cam: (B, 3) ``(s, tx, ty)``.
        thetas: (T + 1, B, P) parameters before the first and after every iteration (T = 0: the mean).
    """

    pose: torch.Tensor
    orient: torch.Tensor
    bone: torch.Tensor
    shape: torch.Tensor
    cam: torch.Tensor
    thetas: torch.Tensor

    def float(self) -> HMROutput:
        """Every field in float32 (after bf16 autocast)."""
        return HMROutput(**{k: v.float() for k, v in vars(self).items()})


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


class HMRBLSM(nn.Module):
    """Backbone + IEF regressor of BLSM parameters (module docstring).

    Args:
        backbone: a name of :func:`recovery.models.backbone.build_backbone`.
        layout: the parameter layout (the BLSM model's DoF and bone counts, ``num_shape``).
        num_model_shape: the model's shape coefficient count Ks (the output is padded with zeros).
        init: (P,) mean parameters ``Theta_0`` (:func:`mean_theta`).
        pretrained: load the backbone's ImageNet weights.
        hidden, dropout, iterations: the regressor (HMR: 1024, 0.5, 3).
    """

    def __init__(self, backbone: str, layout: ParamLayout, num_model_shape: int, init: torch.Tensor,
                 pretrained: bool = False, hidden: int = 1024, dropout: float = 0.5, iterations: int = 3) -> None:
        super().__init__()
        if init.shape != (layout.size,):
            raise ValueError(f"init must be ({layout.size},), got {tuple(init.shape)}")
        self.layout, self.num_model_shape = layout, int(num_model_shape)
        self.backbone = build_backbone(backbone, pretrained=pretrained)
        self.regressor = IEFRegressor(self.backbone.out_channels, init, hidden, dropout, iterations)

    def forward(self, images: torch.Tensor) -> HMROutput:
        """Args: images (B, 3, H, W) RGB in [0, 1] (normalised here). Returns :class:`HMROutput`."""
        thetas = self.regressor(self.backbone(self.backbone.normalize(images)))
        return self.decode(thetas)

    def decode(self, thetas: torch.Tensor) -> HMROutput:
        p = self.layout.split(thetas[-1])
        shape = p["shape"]
        pad = self.num_model_shape - shape.shape[-1]
        if pad > 0:
            shape = torch.cat([shape, shape.new_zeros(shape.shape[0], pad)], dim=-1)
        return HMROutput(pose=p["pose"], orient=rot6d_to_matrix(p["orient"]), bone=p["bone"], shape=shape,
                         cam=p["cam"], thetas=thetas)


@dataclass
class BodyOutput:
    """BLSM evaluated on a prediction (or on labels), camera frame, metres.

    Attributes:
        keypoints_3d: (B, K, 3) relative to the pelvis (the model's root joint).
        vertices: (B, V, 3) relative to the pelvis.
        angles: (B, 47) radians (inside the limits).
        transl: (B, 3) the pelvis' camera-frame position.
        keypoints_2d: (B, K, 2) projected with ``K_crop`` (pixels), when ``k_crop`` was given.
    """

    keypoints_3d: torch.Tensor
    vertices: torch.Tensor
    angles: torch.Tensor
    transl: torch.Tensor | None = None
    keypoints_2d: torch.Tensor | None = None


def body_outputs(body: nn.Module, pose: torch.Tensor, orient: torch.Tensor, bone: torch.Tensor,
                 shape: torch.Tensor, transl: torch.Tensor | None = None, k_crop: torch.Tensor | None = None,
                 keypoints: torch.Tensor | None = None) -> BodyOutput:
    """Run the BLSM ``body`` and place it in the camera frame.

    Args:
        body: a :class:`blsm.BLSM`.
        pose: (B, 47) unconstrained values. orient: (B, 3, 3) or (B, 3) axis-angle, camera frame.
        bone: (B, Kb). shape: (B, Ks).
        transl: (B, 3) pelvis position in the camera frame (needed for ``keypoints_2d``).
        k_crop: (B, 3, 3) intrinsics to project the keypoints with.
        keypoints: (K,) indices into the model's keypoints to keep (None: all).
    """
    from kornia.geometry.conversions import rotation_matrix_to_axis_angle

    aa = rotation_matrix_to_axis_angle(orient) if orient.dim() == 3 else orient
    out = body(pose=pose, bone=bone, shape=shape, global_orient=aa)
    root = out.joints[:, :1]
    kp = out.keypoints - root
    if keypoints is not None:
        kp = kp[:, keypoints]
    res = BodyOutput(keypoints_3d=kp, vertices=out.vertices - root, angles=out.angles, transl=transl)
    if transl is not None and k_crop is not None:
        res.keypoints_2d = project(kp + transl[:, None], k_crop)
    return res


def predict_body(body: nn.Module, pred: HMROutput, k_crop: torch.Tensor, crop: int,
                 keypoints: torch.Tensor | None = None) -> BodyOutput:
    """:func:`body_outputs` of a network prediction, its translation from ``cam`` and ``K_crop``."""
    transl = cam_to_translation(pred.cam, k_crop, crop)
    return body_outputs(body, pred.pose, pred.orient, pred.bone, pred.shape, transl, k_crop, keypoints)


MIRROR_X = torch.diag(torch.tensor([-1.0, 1.0, 1.0]))
"""The horizontal image flip in the camera frame (x -> -x)."""


def unflip_output(body: nn.Module, out: HMROutput) -> HMROutput:
    """A prediction on a horizontally flipped crop, mirrored back to the crop itself.

    The inverse of what :class:`recovery.data.BatchAugment` does to the labels of a flipped crop:
    the 47 atoms mirrored with the model's ``dof_mirror`` (valid for the unconstrained x), the
    camera-frame orientation conjugated by ``diag(-1, 1, 1)``, ``tx`` negated (``u -> S - u`` in
    the crop; ``K_crop`` is that of the unflipped crop); bone and shape coefficients are the
    same for the mirror image (the augmentation keeps them). ``thetas`` are left as predicted.
    """
    m = MIRROR_X.to(out.orient)
    cam = out.cam * out.cam.new_tensor([1.0, -1.0, 1.0])
    return HMROutput(pose=body.mirror_pose(out.pose), orient=m @ out.orient @ m, bone=out.bone, shape=out.shape,
                     cam=cam, thetas=out.thetas)


def flip_average(body: nn.Module, out: HMROutput, flipped: HMROutput) -> HMROutput:
    """Flip test-time augmentation: the mean of a prediction and of the prediction on the
    horizontally flipped crop mirrored back (:func:`unflip_output`), the orientations averaged
    as rotation matrices and projected onto SO(3) (SVD). ``thetas`` are the unflipped pass's."""
    back = unflip_output(body, flipped)
    u, _, vt = torch.linalg.svd(0.5 * (out.orient + back.orient))
    d = torch.linalg.det(u @ vt)
    fix = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    return HMROutput(pose=0.5 * (out.pose + back.pose), orient=u @ fix @ vt, bone=0.5 * (out.bone + back.bone),
                     shape=0.5 * (out.shape + back.shape), cam=0.5 * (out.cam + back.cam), thetas=out.thetas)


UPRIGHT_FACING_CAMERA = torch.diag(torch.tensor([1.0, -1.0, -1.0]))
"""The body's rest frame (Y up, facing +Z) seen upright and facing an OpenCV camera (y down, z
forward): a half turn about x, as HMR's mean global rotation."""


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
