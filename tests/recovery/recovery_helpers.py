"""Constants and helpers of the recovery tests (imported by conftest.py and the test modules)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
import yaml

CROP = 32  # network input of every test network, pixels
CONTEXT = 1.5  # recovery.config.DataConfig's default

# The training run of the trainer / CLI tests: the default EfficientNet-Lite0 without ImageNet
# weights (a quarter of ResNet-18's parameters, so a checkpoint is about 40 MB instead of 150 MB),
# a narrow regressor with dropout, the discriminator and augmentation on, six steps of four.
TRAIN_STEPS = 6


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """One torch thread, and numpy's error handling restored afterwards (``recovery.train.train``
    sets ``np.seterr(all="ignore")`` for the whole process)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with np.errstate():
            yield
    finally:
        torch.set_num_threads(n)


def train_config(fake_root: Path, cache: Path, **changes: dict) -> dict:
    """The tiny run's configuration as a dict; ``changes`` updates sections (``optim={"lr": 1e-3}``)."""
    cfg = {
        "model": {"backbone": "efficientnet_lite0", "pretrained": False, "hidden": 64, "dropout": 0.5},
        "data": {
            "train": [str(fake_root)],
            "val": str(fake_root),
            "crop": CROP,
            "cache": str(cache),
            "workers": 0,
        },
        "discriminator": {"prior_samples": 256},
        "optim": {"warmup_steps": 2},
        "train": {
            "steps": TRAIN_STEPS,
            "batch_size": 4,
            "val_every": 100,
            "checkpoint_every": 100,
            "log_every": 1,
            "device": "cpu",
        },
    }
    for section, values in changes.items():
        cfg[section] = {**cfg[section], **values}
    return cfg


def write_config(path: Path, cfg: dict) -> Path:
    path.write_text(yaml.safe_dump(cfg))
    return path


def sphere(subdivisions: int = 2, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A closed, outward-wound icosphere with radially jittered vertices (no distance ties)."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    rng = np.random.default_rng(seed)
    v = m.vertices * (1 + 0.05 * rng.random((len(m.vertices), 1)))
    return v, np.asarray(m.faces)


def fake_graph_convolutions(state: dict[str, torch.Tensor], node_map: dict, input_dims: list[str]
                            ) -> tuple[list[dict], dict[str, np.ndarray]]:
    """A TF.js graph's input placeholder (``input_dims``, NHWC sizes as strings) and one fused
    convolution node per entry of a MoveNet ``node_map`` (``path -> (node, activation, stride)``,
    :func:`recovery.models.backbones.movenet.graph_node_map`), with the weights of ``state`` in TF's
    layouts (HWIO, depthwise HWCM) and MoveNet's node names (heads outside the feature extractor)."""
    import base64

    from recovery.models.backbones.movenet import GRAPH_PREFIX

    dims = [{"size": s} for s in input_dims]
    nodes: list[dict] = [{"name": "input", "op": "Placeholder", "attr": {"shape": {"shape": {"dim": dims}}}}]
    weights: dict[str, np.ndarray] = {}
    for path, (node, act, stride) in node_map.items():
        head = node.split("/")[0].endswith("_0")  # kpt_heatmap_0, center_0, box_scale_0, ...
        full = (GRAPH_PREFIX[1] if head else GRAPH_PREFIX[0]) + node
        w = state[path + ".weight"]
        depthwise = w.shape[1] == 1 and w.shape[0] > 1 and w.shape[-1] == 3
        weights[full + "/k"] = (w.permute(2, 3, 0, 1) if depthwise else w.permute(2, 3, 1, 0)).numpy()
        inputs = ["prev", full + "/k"]
        if path + ".bias" in state:
            weights[full + "/b"] = state[path + ".bias"].numpy()
            inputs.append(full + "/b")
        fused = [base64.b64encode(f.encode()).decode() for f in ["BiasAdd"] + ([act] if act else [])]
        nodes.append({"name": full, "op": "FusedDepthwiseConv2dNative" if depthwise else "_FusedConv2D",
                      "input": inputs, "attr": {"strides": {"list": {"i": ["1", str(stride), str(stride), "1"]}},
                                                "fused_ops": {"list": {"s": fused}}}})
    return nodes, weights
