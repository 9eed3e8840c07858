"""The network each recovery task trains and predicts with, by the task's name (a config's and a
checkpoint's ``task``): :func:`build_network` builds the network of a config; training
(:mod:`recovery.tasks`) and inference (:mod:`recovery.predictor`) both come here, so inference needs
the models alone and no training module.

A task with an inference network registers its builder with one line, ``NETWORKS["name"] = builder``;
a task without one (the mesh autoencoder) is absent.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import nn

from recovery.config import RecoveryConfig
from recovery.mesh.operators import mesh_operators
from recovery.models.heads import ParamLayout
from recovery.models.hmr import HMRBLSM
from recovery.models.mesh_net import MeshRegressor

__all__ = ["NETWORKS", "build_hmr", "build_network", "inference_tasks"]

NetworkBuilder = Callable[[RecoveryConfig, nn.Module, Path, Any], tuple[nn.Module, torch.Tensor | None]]
"""``(cfg, body, model_path, log) -> (network, keypoint regressor (K, V) or None)``: the network of a
config, its weights not loaded (a checkpoint's follow; training initialises its own)."""


def build_hmr(cfg: RecoveryConfig, body: nn.Module, init: torch.Tensor | None = None,
              pretrained: bool | None = None) -> HMRBLSM:
    """HMR-BLSM of ``cfg.model`` for the BLSM ``body``; ``init`` = Theta_0 (zeros when loading a
    checkpoint); ``pretrained``: the backbone's own weights (default: ``cfg.model.pretrained``)."""
    m = cfg.model
    if m.num_shape > body.num_shape_coeffs:
        raise ValueError(f"model.num_shape {m.num_shape} exceeds the model's {body.num_shape_coeffs} shape coefficients")
    layout = ParamLayout(body.num_dofs, body.num_bone_coeffs, m.num_shape)
    if init is None:
        init = torch.zeros(layout.size)
    return HMRBLSM(m.backbone, layout, body.num_shape_coeffs, init, pretrained=m.pretrained if pretrained is None else pretrained,
                   hidden=m.hidden, dropout=m.dropout, iterations=m.ief_iterations, head_input=m.head_input,
                   image_dropout=m.image_dropout, keypoint_width=m.keypoint_width, train_blocks=m.train_blocks)


def _hmr_network(cfg: RecoveryConfig, body: nn.Module, model_path: Path, log: Any = print) -> tuple[nn.Module, None]:
    """HMR-BLSM without its backbone's pretrained weights (the checkpoint's are loaded next)."""
    return build_hmr(cfg, body, pretrained=False), None


def _mesh_network(cfg: RecoveryConfig, body: nn.Module, model_path: Path,
                  log: Any = print) -> tuple[nn.Module, torch.Tensor]:
    """The image-to-mesh network of a config (its weights, normalisation and camera bias are loaded
    next) and its keypoint regressor (K, V)."""
    ops = mesh_operators(model_path, cfg.mesh.cache, cfg.mesh.ops_settings(), log=log)
    nv = body.num_vertices
    m = cfg.mesh
    model = MeshRegressor(cfg.model.backbone, ops, torch.zeros(nv, 3), torch.ones(nv, 3), torch.zeros(3),
                          pretrained=False, channels=tuple(m.channels), latent=m.latent, hidden=m.hidden)
    return model, torch.as_tensor(ops.regressor)


NETWORKS: dict[str, NetworkBuilder] = {}
NETWORKS["hmr_blsm"] = _hmr_network
NETWORKS["mesh"] = _mesh_network


def inference_tasks() -> tuple[str, ...]:
    """The tasks whose checkpoints predict, in registration order."""
    return tuple(NETWORKS)


def build_network(cfg: RecoveryConfig, body: nn.Module, model_path: Path,
                  log: Any = print) -> tuple[nn.Module, torch.Tensor | None]:
    """The inference network of ``cfg.task`` (:data:`NETWORKS`); a ValueError for a task without one."""
    if cfg.task not in NETWORKS:
        raise ValueError(f"task {cfg.task!r} has no inference network; tasks that predict: {', '.join(NETWORKS)}")
    return NETWORKS[cfg.task](cfg, body, model_path, log)
