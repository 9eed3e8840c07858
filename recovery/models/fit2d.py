"""Test-time fitting of a network's BLSM prediction to 2D keypoints (SMPLify-style, from the regression).

HMR-style regressors put the body roughly where the person is; a few steps of optimisation bring its
projected keypoints onto detected ones. SMPLify (Bogo et al., ECCV 2016) does this from a mean pose; SPIN
(Kolotouros et al., ICCV 2019) and EFT start from the regression, as here. The detected keypoints are
MoveNet's (trained on photographs), so the fit moves the body towards what a photo-trained detector sees,
while the regression's 3D (depth, orientation, bone and shape) is kept by a prior that pulls every fitted
value back towards the network's answer.

Fitted: the 47 unconstrained pose values x (Eq. 6 keeps the angles inside the limits), the orientation
(6-D) and the weak-perspective camera ``(s, tx, ty)``; bone and shape stay the network's. The energy, per
person, with ``r_j`` the projected keypoint ``j`` minus the detected one over the crop side:

    E = sum_j w_j rho(|r_j|) + lambda_pose |x - x0|^2 / 47 + lambda_orient |o - o0|^2 + lambda_cam |c - c0|^2

``w_j`` the detection's confidence where it is at least ``min_confidence`` (else 0), ``rho`` the
Geman-McClure function ``r^2 / (r^2 + sigma^2)`` (SMPLify's robust 2D term), ``sigma`` = ``robust`` of
the crop. A person with fewer than ``min_joints`` confident keypoints keeps the regression.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from recovery.models.hmr import HMROutput, predict_body
from recovery.utils.geometry import matrix_to_rot6d, rot6d_to_matrix


@dataclass(frozen=True)
class FitSettings:
    """The fit's iterations (0: off), step and weights (module docstring)."""

    iterations: int = 30
    lr: float = 0.03
    min_confidence: float = 0.3
    min_joints: int = 6
    robust: float = 0.05
    pose_weight: float = 0.05
    orient_weight: float = 0.5
    cam_weight: float = 1.0


def fit_to_keypoints(
    body: nn.Module,
    pred: HMROutput,
    k_crop: torch.Tensor,
    crop: int,
    detected: torch.Tensor,
    model_ids: list[int] | torch.Tensor,
    settings: FitSettings = FitSettings(),
) -> HMROutput:
    """The prediction fitted to ``detected`` keypoints (module docstring).

    Args:
        body: the BLSM model. pred: the network's prediction (camera frame).
        k_crop: (B, 3, 3) the crops' intrinsics. crop: the crop side, pixels.
        detected: (B, J, 3) keypoints ``(u, v, confidence)`` in crop pixels.
        model_ids: (J,) the model keypoint index of each detected keypoint.

    Returns:
        A new :class:`HMROutput` (``thetas`` the network's); people without enough confident keypoints
        unchanged.
    """
    if settings.iterations <= 0:
        return pred
    ids = torch.as_tensor(model_ids, dtype=torch.long, device=detected.device)
    conf = detected[..., 2]
    w = torch.where(conf >= settings.min_confidence, conf, torch.zeros_like(conf))
    use = (w > 0).sum(-1) >= settings.min_joints
    if not use.any():
        return pred
    x0, o0, c0 = pred.pose.detach(), matrix_to_rot6d(pred.orient.detach()), pred.cam.detach()
    x, o, c = (t.clone().requires_grad_(True) for t in (x0, o0, c0))
    opt = torch.optim.Adam([x, o, c], lr=settings.lr)
    target = detected[..., :2]
    for _ in range(settings.iterations):
        with torch.enable_grad():
            cur = HMROutput(
                pose=x,
                orient=rot6d_to_matrix(o),
                bone=pred.bone.detach(),
                shape=pred.shape.detach(),
                cam=c,
                thetas=pred.thetas,
            )
            uv = predict_body(body, cur, k_crop, crop, ids).keypoints_2d
            r2 = ((uv - target) / crop).square().sum(-1)
            data = (w * r2 / (r2 + settings.robust**2)).sum(-1)
            prior = (
                settings.pose_weight * (x - x0).square().mean(-1)
                + settings.orient_weight * (o - o0).square().sum(-1)
                + settings.cam_weight * (c - c0).square().sum(-1)
            )
            loss = ((data + prior) * use).sum()
            opt.zero_grad()
            loss.backward()
        opt.step()
    keep = use[:, None]
    with torch.no_grad():
        pose = torch.where(keep, x, x0)
        orient = torch.where(keep[..., None], rot6d_to_matrix(o), pred.orient)
        cam = torch.where(keep, c, c0)
    return HMROutput(
        pose=pose.detach(),
        orient=orient.detach(),
        bone=pred.bone,
        shape=pred.shape,
        cam=cam.detach(),
        thetas=pred.thetas,
    )
