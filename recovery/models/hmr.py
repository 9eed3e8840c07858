"""HMR-BLSM: HMR's regressor (Kanazawa et al. 2018) with its SMPL head replaced by BLSM (thesis
Sec. 6.4.3).

Image evidence (``head_input``): the backbone's pooled features (HMR), or, on a MoveNet backbone,
MoveNet's own 2D keypoints and confidences through :class:`KeypointEncoder` (a lifting network, as
keypoint-conditioned regressors do), optionally with the pooled features or per-keypoint features of
the stride-4 map (:class:`PartPool`) as a secondary input ->
iterative error feedback (:mod:`recovery.models.heads`): starting from
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

from recovery.models.backbones import MoveNet, build_backbone
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


class KeypointEncoder(nn.Module):
    """MoveNet's 17 keypoints ``(x, y, score)`` (and optionally pooled image features) -> one vector.

    The keypoints are given in crop pixels and mapped to [-1, 1] (``2 u / S - 1``); with the scores
    they pass two fully connected layers of ``width`` with ReLU. Image features, when given, are
    layer-normalised, projected to ``width`` with ReLU, and in training dropped per image with
    probability ``image_dropout`` (the survivors rescaled by ``1 / (1 - p)``, as dropout does), so the
    regressor cannot lean on appearance alone; the output is the concatenation.
    """

    def __init__(self, num_keypoints: int, width: int = 256, image_features: int = 0, image_dropout: float = 0.0) -> None:
        super().__init__()
        self.keypoints = nn.Sequential(nn.Linear(3 * num_keypoints, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU())
        self.image = None
        if image_features:
            self.image = nn.Sequential(nn.LayerNorm(image_features), nn.Linear(image_features, width), nn.ReLU())
        self.image_dropout = float(image_dropout)
        self.out_features = width * (2 if image_features else 1)

    def forward(self, keypoints: torch.Tensor, size: float, image: torch.Tensor | None = None) -> torch.Tensor:
        """keypoints (B, K, 3) in pixels of an S = ``size`` crop; image (B, C) or None -> (B, out_features)."""
        xy = keypoints[..., :2] * (2.0 / size) - 1.0
        x = self.keypoints(torch.cat([xy, keypoints[..., 2:]], -1).flatten(1))
        if self.image is None:
            return x
        if image is None:
            raise ValueError("this encoder was built with image features; pass them")
        f = self.image(image)
        if self.training and self.image_dropout > 0:
            keep = (torch.rand(f.shape[0], 1, device=f.device) >= self.image_dropout).to(f.dtype)
            f = f * keep / (1.0 - self.image_dropout)
        return torch.cat([x, f], -1)


class PartPool(nn.Module):
    """A spatial head over MoveNet's stride-4 pyramid map: a 3x3 convolution (``width`` channels, ReLU),
    then one feature vector per keypoint, its map averaged under a spatial softmax of MoveNet's own
    heatmap logits for that keypoint (a soft read-out at the joint, as part-attention regressors do,
    e.g. PARE's part-guided attention, here with MoveNet's heatmaps as the attention).
    """

    def __init__(self, channels: int, num_keypoints: int = 17, width: int = 64) -> None:
        super().__init__()
        self.conv = nn.Sequential(nn.Conv2d(channels, width, 3, padding=1), nn.ReLU())
        self.out_features = num_keypoints * width

    def forward(self, p4: torch.Tensor, heatmap: torch.Tensor) -> torch.Tensor:
        """p4 (B, C, h, w), heatmap logits (B, K, h, w) -> (B, K * width)."""
        f = self.conv(p4).flatten(2)  # (B, W, hw)
        a = torch.softmax(heatmap.flatten(2).to(f.dtype), dim=-1)  # (B, K, hw)
        return torch.einsum("bkn,bwn->bkw", a, f).flatten(1)


class HMRBLSM(nn.Module):
    """Backbone + IEF regressor of BLSM parameters (module docstring).

    Args:
        backbone: a name of :func:`recovery.models.backbones.build_backbone`.
        layout: the parameter layout (the BLSM model's DoF and bone counts, ``num_shape``).
        num_model_shape: the model's shape coefficient count Ks (the output is padded with zeros).
        init: (P,) mean parameters ``Theta_0`` (:func:`recovery.models.heads.mean_theta`).
        pretrained: load the backbone's pretrained weights (ImageNet; MoveNet's own).
        hidden, dropout, iterations: the regressor (HMR: 1024, 0.5, 3).
        head_input: ``pooled``, ``keypoints``, ``keypoints+pooled`` or ``keypoints+parts``
            (:class:`recovery.config.ModelConfig`; ``parts``: :class:`PartPool` over the stride-4 map).
        image_dropout, keypoint_width: the :class:`KeypointEncoder`'s.
        train_blocks: -1 every backbone weight trains; 0 none (the backbone runs without gradients);
            N > 0 (MoveNet) the last N trunk blocks and what follows them.
    """

    def __init__(self, backbone: str, layout: ParamLayout, num_model_shape: int, init: torch.Tensor,
                 pretrained: bool = False, hidden: int = 1024, dropout: float = 0.5, iterations: int = 3,
                 head_input: str = "pooled", image_dropout: float = 0.0, keypoint_width: int = 256,
                 train_blocks: int = -1) -> None:
        super().__init__()
        if init.shape != (layout.size,):
            raise ValueError(f"init must be ({layout.size},), got {tuple(init.shape)}")
        self.layout, self.num_model_shape = layout, int(num_model_shape)
        self.backbone = build_backbone(backbone, pretrained=pretrained)
        self.head_input = head_input
        self.encoder: KeypointEncoder | None = None
        self.parts: PartPool | None = None
        width = self.backbone.out_channels
        if head_input != "pooled":
            if not isinstance(self.backbone, MoveNet):
                raise ValueError(f"head_input {head_input!r} needs a MoveNet backbone, got {backbone!r}")
            image = self.backbone.out_channels if head_input == "keypoints+pooled" else 0
            if head_input == "keypoints+parts":
                self.parts = PartPool(self.backbone.p4_channels)
                image = self.parts.out_features
            self.encoder = KeypointEncoder(17, keypoint_width, image, image_dropout)
            width = self.encoder.out_features
        self.regressor = IEFRegressor(width, init, hidden, dropout, iterations)
        self.train_blocks = int(train_blocks)
        self._freeze()

    def _freeze(self) -> None:
        if self.train_blocks < 0:
            return
        for p in self.backbone.parameters():
            p.requires_grad_(False)
        if self.train_blocks > 0:
            if not isinstance(self.backbone, MoveNet):
                raise ValueError("train_blocks > 0 needs a MoveNet backbone")
            b = self.backbone
            for m in (*b.blocks[len(b.blocks) - self.train_blocks:], b.head_conv, b.fpn_top, b.lateral16, b.lateral8,
                      b.lateral4, b.smooth16, b.smooth8, b.smooth4, b.heads):
                for p in m.parameters():
                    p.requires_grad_(True)

    def train(self, mode: bool = True) -> HMRBLSM:
        super().train(mode)
        if self.train_blocks == 0:
            self.backbone.eval()  # a fixed backbone keeps its BatchNorm statistics
        return self

    def evidence(self, images: torch.Tensor, guide: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(B, 3, H, W) RGB in [0, 1] -> the regressor's input (B, C) and, with a keypoint head, MoveNet's
        keypoints (B, 17, 3) ``(u, v, score)`` in pixels of the crop (else None). ``guide`` (B, 17, 3):
        a detector's keypoints of the wanted person, crop pixels (:meth:`MoveNet.keypoints`)."""
        x = self.backbone.normalize(images)
        with torch.set_grad_enabled(torch.is_grad_enabled() and self.train_blocks != 0):
            if self.encoder is None:
                return self.backbone(x), None
            out = self.backbone.run(x)
            kp = self.backbone.keypoints(out, soft=True, guide=guide)
        if self.parts is not None:  # pooled per part; trains even with the backbone fixed
            image = self.parts(out.p4, out.heatmap)
        elif self.encoder.image is not None:
            image = out.c32.mean(dim=(2, 3))
        else:
            image = None
        return self.encoder(kp, float(images.shape[-1]), image), kp

    def features(self, images: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) RGB in [0, 1] -> the regressor's input (B, C)."""
        return self.evidence(images)[0]

    def forward(self, images: torch.Tensor) -> HMROutput:
        """Args: images (B, 3, H, W) RGB in [0, 1] (normalised here). Returns :class:`HMROutput`."""
        return self.decode(self.regressor(self.features(images)))

    def forward_keypoints(self, images: torch.Tensor, guide: torch.Tensor | None = None
                          ) -> tuple[HMROutput, torch.Tensor | None]:
        """:meth:`forward` and the keypoints of :meth:`evidence` (None without a keypoint head)."""
        f, kp = self.evidence(images, guide)
        return self.decode(self.regressor(f)), kp

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
