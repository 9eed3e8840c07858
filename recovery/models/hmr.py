"""HMR-BLSM: HMR's regressor (Kanazawa et al. 2018) with its SMPL head replaced by BLSM (thesis
Sec. 6.4.3).

Pooled backbone features -> iterative error feedback (:mod:`recovery.models.heads`): starting from
the mean parameters ``Theta_0``, each of ``ief_iterations`` steps regresses a correction from
``[features, Theta_t]`` through two FC layers of ``hidden`` units with ReLU and dropout,
``Theta_{t+1} = Theta_t + dTheta``, ``Theta`` laid out by :class:`recovery.models.heads.ParamLayout`.

:func:`body_outputs` runs BLSM on the prediction: keypoints and vertices relative to the pelvis in
the camera frame, the translation, and the 2D keypoints projected with ``K_crop``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from recovery.models.backbones import build_backbone
from recovery.models.heads import IEFRegressor, ParamLayout
from recovery.utils.geometry import cam_to_translation, project, rot6d_to_matrix


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


class HMRBLSM(nn.Module):
    """Backbone + IEF regressor of BLSM parameters (module docstring).

    Args:
        backbone: a name of :func:`recovery.models.backbones.build_backbone`.
        layout: the parameter layout (the BLSM model's DoF and bone counts, ``num_shape``).
        num_model_shape: the model's shape coefficient count Ks (the output is padded with zeros).
        init: (P,) mean parameters ``Theta_0`` (:func:`recovery.models.heads.mean_theta`).
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

    The inverse of what :class:`recovery.datasets.augment.BatchAugment` does to the labels of a flipped crop:
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
