"""The interface of the image backbones: normalised images ``(B, 3, H, W)`` -> globally average-pooled
features ``(B, C)``, with the input normalisation each expects (``input_mean`` / ``input_std``, per
RGB channel, for pixel values in [0, 1]).
"""

from __future__ import annotations

import abc

import torch
from torch import nn

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
"""The RGB statistics of ImageNet for pixels in [0, 1], the input normalisation of ImageNet-trained
backbones (torchvision's ResNets; EfficientNet-Lite and MoveNet have their own)."""


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
