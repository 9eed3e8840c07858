"""Find the people in a photograph: MoveNet MultiPose (:mod:`recovery.models.movenet_multipose`) on the
image scaled to a fixed longer side, its people mapped back to image pixels and kept above a score.

Input size policy (MoveNet's own for MultiPose, as TF.js ``pose-detection`` runs it): the image is
scaled so that its longer side is ``size`` pixels (default 256, MoveNet's recommendation; 128 to 512,
a multiple of 32) keeping its aspect ratio, the shorter side rounded to whole pixels, then padded with
black on the bottom or right to the next multiple of 32. The scaling is bilinear with antialiasing
(``torch.nn.functional.interpolate(antialias=True)``, half-pixel centres): TF.js resizes without a
prefilter, which aliases a large photograph; both map pixel centres alike, so coordinates go back by the
per-axis scale alone. Larger ``size`` finds smaller people at about the square of the cost.

A person is kept when its score (the centre peak times the mean of its confident keypoint scores,
:func:`recovery.models.movenet_multipose.decode_multipose`) is at least ``min_score``: 0.25 by
default, the ``minPoseScore`` default of TF.js ``pose-detection`` for MoveNet. Its box is clipped to
the image; people are returned by descending score.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from recovery.models.movenet_multipose import MoveNetMultiPose, build_multipose

MIN_SCORE = 0.25
"""Default person score threshold (TF.js pose-detection's ``minPoseScore`` for MoveNet)."""
SIZE = 256
"""Default longer side of the detector's input, pixels (MoveNet MultiPose's recommendation)."""


@dataclass
class Detection:
    """One person found in an image (image pixels, pixel centres at integer + 0.5).

    Attributes:
        box: (4,) ``x0, y0, x1, y1``.
        score: the person score in [0, 1].
        keypoints: (17, 3) COCO keypoints ``(x, y, score)``
            (:data:`recovery.models.backbones.movenet.COCO_KEYPOINTS`).
    """

    box: np.ndarray
    score: float
    keypoints: np.ndarray


def letterbox(image: np.ndarray, size: int = SIZE) -> tuple[torch.Tensor, tuple[float, float]]:
    """(H, W, 3) uint8 RGB -> the detector's input (1, 3, H', W') in 0..255 (longer side ``size``,
    padded with black to multiples of 32) and the per-axis scales ``(sx, sy)`` from image to input."""
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3), got {image.shape}")
    h, w = image.shape[:2]
    s = size / max(h, w)
    nh, nw = max(1, round(h * s)), max(1, round(w * s))
    x = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float()
    x = F.interpolate(x, size=(nh, nw), mode="bilinear", align_corners=False, antialias=nh < h or nw < w)
    ph, pw = -(-nh // 32) * 32, -(-nw // 32) * 32
    x = F.pad(x.clamp(0, 255), (0, pw - nw, 0, ph - nh))
    return x, (nw / w, nh / h)


class PersonDetector:
    """MoveNet MultiPose behind :meth:`__call__`: an image in, its people out (module docstring).

    Args:
        size: longer side of the detector's input in pixels (a multiple of 32, 128 to 512).
        min_score: the person score threshold in [0, 1].
        net: the network (default: :func:`build_multipose` with its committed weights).
    """

    def __init__(self, size: int = SIZE, min_score: float = MIN_SCORE,
                 net: MoveNetMultiPose | None = None) -> None:
        if size % 32 or not 128 <= size <= 512:
            raise ValueError(f"the detector's size must be a multiple of 32 in [128, 512], got {size}")
        if not 0.0 <= min_score <= 1.0:
            raise ValueError(f"the person score threshold must be in [0, 1], got {min_score}")
        self.size, self.min_score = size, min_score
        self.net = net if net is not None else build_multipose()

    @torch.no_grad()
    def __call__(self, image: np.ndarray) -> list[Detection]:
        """(H, W, 3) uint8 RGB -> the people scoring at least ``min_score``, best first."""
        h, w = image.shape[:2]
        x, (sx, sy) = letterbox(image, self.size)
        out = self.net(self.net.normalize(x))
        scale = torch.tensor([sx, sy, sx, sy])
        boxes = out.boxes[0] / scale
        boxes[:, 0::2] = boxes[:, 0::2].clamp(0, w)
        boxes[:, 1::2] = boxes[:, 1::2].clamp(0, h)
        kps = out.keypoints[0].clone()
        kps[..., 0] /= sx
        kps[..., 1] /= sy
        found = []
        for i in torch.argsort(out.scores[0], descending=True, stable=True).tolist():
            score = float(out.scores[0, i])
            b = boxes[i]
            if score < self.min_score or score <= 0 or b[2] <= b[0] or b[3] <= b[1]:  # fill; in the padding
                continue
            found.append(Detection(box=b.numpy().astype(np.float64), score=score,
                                   keypoints=kps[i].numpy().astype(np.float64)))
        return found
