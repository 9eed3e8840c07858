"""MoveNet (recovery.models.backbones.movenet): the converted weights on a real photograph, the TF.js
reader, the graph-to-module conversion, and HMR-BLSM on MoveNet's keypoints."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from recovery_helpers import fake_graph_convolutions

from recovery.models.backbones import build_backbone
from recovery.models.backbones.movenet import (
    COCO_KEYPOINTS,
    VARIANTS,
    MoveNet,
    graph_node_map,
    movenet_weights_path,
    state_dict_from_graph,
)
from recovery.models.backbones.tfjs import read_graph_model, write_graph_model

# MoveNet's keypoints on scikit-image's astronaut (512 x 512, resized to the net's input with Pillow's
# bilinear filter), in input pixels, as converted on 2026-12-06 and checked by eye on an overlay (eyes,
# nose, ears, shoulders and elbows where Eileen Collins' are; hips and knees hidden by the helmet, low
# scores). Lightning at 192 px, Thunder at 256 px. Rows: COCO order; x, y, score.
ASTRONAUT = {
    "movenet_lightning": [
        [83.24, 45.48, 0.58],
        [92.46, 37.93, 0.73],
        [76.49, 37.05, 0.74],
        [103.51, 43.17, 0.49],
        [65.97, 41.62, 0.74],
        [119.22, 101.73, 0.61],
        [40.86, 95.99, 0.64],
        [120.27, 149.20, 0.19],
        [22.77, 153.80, 0.42],
        [102.34, 180.57, 0.31],
        [53.31, 182.79, 0.25],
        [92.43, 187.97, 0.44],
        [47.93, 188.10, 0.36],
        [120.39, 190.18, 0.05],
        [23.89, 186.61, 0.02],
        [93.06, 188.73, 0.09],
        [61.49, 188.45, 0.10],
    ],
    "movenet_thunder": [
        [112.00, 61.53, 0.60],
        [123.43, 51.19, 0.63],
        [102.20, 50.80, 0.84],
        [136.93, 58.82, 0.74],
        [88.25, 55.29, 0.58],
        [158.64, 138.01, 0.83],
        [51.83, 133.65, 0.76],
        [162.66, 203.45, 0.18],
        [32.56, 210.10, 0.55],
        [146.95, 248.52, 0.17],
        [70.80, 246.19, 0.43],
        [131.87, 253.16, 0.27],
        [78.78, 253.41, 0.31],
        [136.97, 220.16, 0.00],
        [58.46, 235.34, 0.01],
        [111.50, 260.06, 0.01],
        [81.10, 258.41, 0.02],
    ],
}
# Drawn by hand on the 512 px photograph: her face, and where her shoulders are.
FACE_BOX = (180, 60, 290, 160)
SHOULDERS = {"left_shoulder": (318, 272), "right_shoulder": (106, 262)}


def _astronaut(size: int) -> torch.Tensor:
    skimage_data = pytest.importorskip("skimage.data")
    from PIL import Image

    img = np.asarray(Image.fromarray(skimage_data.astronaut()).resize((size, size), Image.BILINEAR)).copy()
    return torch.from_numpy(img).permute(2, 0, 1)[None].float() / 255.0


@pytest.mark.parametrize("name", list(VARIANTS))
def test_converted_movenet_finds_the_astronaut(name: str) -> None:
    net = build_backbone(name, pretrained=True).eval()
    x = _astronaut(net.input_size)
    with torch.no_grad():
        out = net.run(net.normalize(x))
        kp = net.keypoints(out)[0]
        soft = net.keypoints(out, soft=True)[0]
    want = torch.tensor(ASTRONAUT[name])
    confident = want[:, 2] > 0.3
    assert confident.sum() >= 9
    assert torch.allclose(kp[confident, :2], want[confident, :2], atol=0.5), (kp - want)[confident]
    assert torch.allclose(kp[:, 2], want[:, 2], atol=0.02)
    # independent of the stored numbers: the face and shoulders drawn by hand
    px = kp[:, :2] * (512 / net.input_size)
    for k in ("nose", "left_eye", "right_eye"):
        x0, y0, x1, y1 = FACE_BOX
        u, v = px[COCO_KEYPOINTS.index(k)].tolist()
        assert x0 <= u <= x1 and y0 <= v <= y1, (k, u, v)
    for k, (u, v) in SHOULDERS.items():
        assert np.hypot(*(px[COCO_KEYPOINTS.index(k)].numpy() - (u, v))) < 20, k
    # the soft read-out stays within a cell of the graph's and keeps its scores
    assert (soft[:, :2] - kp[:, :2]).norm(dim=-1).max() < 4.0
    assert torch.equal(soft[:, 2], kp[:, 2])
    # the pooled trunk and the maps have the documented shapes
    s = net.input_size
    assert out.c32.shape == (1, 1280, s // 32, s // 32) and out.p4.shape == (1, 24, s // 4, s // 4)
    assert out.heatmap.shape[1:] == (17, s // 4, s // 4) and out.offset.shape[1] == 34
    assert net(net.normalize(x)).shape == (1, 1280)


def test_graph_model_reader_round_trip_and_truncation(tmp_path) -> None:
    rng = np.random.default_rng(0)
    weights = {
        "a/kernel": rng.normal(size=(3, 3, 4, 8)).astype(np.float32),
        "b/bias": rng.normal(size=(8,)).astype(np.float32),
        "shape": np.array([1, -1, 17], np.int32),
    }
    path = write_graph_model(
        tmp_path / "m.json", weights, nodes=[{"name": "x", "op": "Placeholder", "attr": {}}]
    )
    g = read_graph_model(path)
    assert list(g.weights) == list(weights)
    for k, v in weights.items():
        want = v.astype(np.float16).astype(np.float32) if v.dtype.kind == "f" else v
        assert np.array_equal(g.weights[k], want) and g.weights[k].shape == v.shape
    assert g.quantization["a/kernel"] == "float16" and g.quantization["shape"] is None
    assert [n["name"] for n in g.nodes] == ["x"]
    shard = tmp_path / "m.bin"
    data = shard.read_bytes()
    shard.write_bytes(data[:-2])
    with pytest.raises(ValueError, match="end inside weight shape"):
        read_graph_model(path)
    shard.write_bytes(data + b"\0\0")
    with pytest.raises(ValueError, match="hold"):
        read_graph_model(path)
    shard.unlink()
    with pytest.raises(ValueError, match="missing"):
        read_graph_model(path)


def _fake_graph(net: MoveNet, name: str, tmp_path) -> tuple:
    """A TF.js graph with MoveNet's node names, TF layouts and constants, made from ``net``'s weights."""
    size = str(net.input_size)
    nodes, weights = fake_graph_convolutions(net.state_dict(), graph_node_map(name), ["1", size, size, "3"])
    h = net.input_size // 4
    weights["ConstantFolding/StatefulPartitionedCall/truediv_2_recip"] = MoveNet.center_prior(h, h)[
        ..., None
    ].numpy()
    for k, v in {
        "Reshape": np.zeros((1, 1, 1, 3)),
        "truediv": np.full((1, 1, 1, 3), 1 / 127.5),
        "Reshape_13": np.full((1, 1, 1, 2), 1 / h),
    }.items():
        weights["StatefulPartitionedCall/" + k] = v.astype(np.float32)
    for i in (3, 4):
        weights[f"StatefulPartitionedCall/strided_slice_{i}"] = np.zeros((h, h, 1), np.float32)
    return nodes, weights


def test_graph_to_module_conversion_round_trip(tmp_path) -> None:
    name = "movenet_lightning"
    torch.manual_seed(0)
    net = MoveNet(name)
    nodes, weights = _fake_graph(net, name, tmp_path)
    path = write_graph_model(tmp_path / "movenet.json", weights, nodes)
    state = state_dict_from_graph(read_graph_model(path), name)
    want = {k: v.half().float() for k, v in net.state_dict().items()}
    assert set(state) == set(want)
    assert all(torch.equal(state[k], want[k]) for k in want)
    # a node with another activation, an unused weight and another input size are refused
    bad = [dict(n) for n in nodes]
    i = next(j for j, n in enumerate(bad) if n["name"].endswith("out_relu/Relu6"))
    bad[i] = {**bad[i], "attr": {**bad[i]["attr"], "fused_ops": {"list": {"s": []}}}}
    with pytest.raises(ValueError, match="activation"):
        state_dict_from_graph(read_graph_model(write_graph_model(tmp_path / "bad.json", weights, bad)), name)
    extra = {**weights, "StatefulPartitionedCall/stray/kernel": np.ones((2, 2), np.float32)}
    with pytest.raises(ValueError, match="not used"):
        state_dict_from_graph(
            read_graph_model(write_graph_model(tmp_path / "extra.json", extra, nodes)), name
        )
    with pytest.raises(ValueError, match="input"):
        state_dict_from_graph(read_graph_model(path), "movenet_thunder")


def test_committed_weights_are_the_documented_files() -> None:
    for name in VARIANTS:
        path = movenet_weights_path(name)
        state = torch.load(path, map_location="cpu", weights_only=True)
        assert all(v.dtype == torch.float16 for v in state.values())
        assert set(state) == set(MoveNet(name).state_dict())
    assert (movenet_weights_path("movenet_lightning").parent / "NOTICE").is_file()
    with pytest.raises(ValueError, match="unknown MoveNet"):
        movenet_weights_path("movenet_fast")


def test_keypoints_follow_a_shift_of_the_image() -> None:
    """Shift the photograph by 8 px: the confident keypoints move by 8 px (the decoding's scale)."""
    net = build_backbone("movenet_lightning", pretrained=True).eval()
    x = _astronaut(192 + 16)
    with torch.no_grad():
        a = net.keypoints(net.run(net.normalize(x[..., 8:200, 8:200])), soft=True)[0]
        b = net.keypoints(net.run(net.normalize(x[..., 0:192, 0:192])), soft=True)[0]
    ok = (a[:, 2] > 0.4) & (b[:, 2] > 0.4)
    assert ok.sum() >= 6
    shift = (b[ok, :2] - a[ok, :2]).median(0).values
    assert torch.allclose(shift, torch.tensor([8.0, 8.0]), atol=1.5), shift


# -- HMR-BLSM on MoveNet -------------------------------------------------------------------------------


def _hmr(model, **kw):
    from recovery.config import ModelConfig, RecoveryConfig
    from recovery.models.registry import build_hmr

    return build_hmr(RecoveryConfig(model=ModelConfig(backbone="movenet_lightning", **kw)), model)


def test_keypoint_head_gets_movenet_keypoints_and_a_fixed_backbone_gets_no_gradient(model) -> None:
    net = _hmr(model, head_input="keypoints+pooled", image_dropout=0.5, train_blocks=0, hidden=32).train()
    assert net.encoder is not None and net.encoder.out_features == 512
    x = _astronaut(64)
    out = net(x.expand(4, -1, -1, -1))
    (out.pose.square().sum() + out.cam.square().sum()).backward()
    assert all(p.grad is None for p in net.backbone.parameters())
    assert all(p.grad is not None for p in net.encoder.keypoints.parameters())
    assert not net.backbone.training and net.regressor.training
    # the encoder reads the keypoints MoveNet decodes (in pixels of the crop) and moves with them
    with torch.no_grad():
        o = net.backbone.run(net.backbone.normalize(x))
        kp = net.backbone.keypoints(o, soft=True)
        net.eval()
        f = net.features(x)
        moved = kp.clone()
        moved[..., 0] += 8
        g = net.encoder(moved, 64.0, o.c32.mean((2, 3)))
    assert torch.allclose(f, net.encoder(kp, 64.0, o.c32.mean((2, 3))), atol=1e-5)
    assert not torch.allclose(f[:, :256], g[:, :256])
    assert torch.allclose(f[:, 256:], g[:, 256:])


def test_a_guide_steers_the_decoding_to_its_person_in_a_crop_of_two() -> None:
    """Two people in one crop, the neighbour with the stronger centre: MoveNet takes the neighbour; given
    the wanted person's keypoints (a detector's), the decoding reads that person."""
    from recovery.models.backbones.movenet import COCO_KEYPOINTS, MoveNetOutput, flip_coco

    net = MoveNet("movenet_lightning")
    h = w = 12
    heat = torch.full((1, 17, h, w), -10.0)
    heat[..., 3, 3] = heat[..., 8, 8] = 5.0  # every joint of A at cell (3, 3), of B at (8, 8)
    center = torch.full((1, 1, h, w), -10.0)
    center[..., 3, 3], center[..., 8, 8] = 0.0, 3.0
    zeros = torch.zeros(1, 34, h, w)
    out = MoveNetOutput(c32=torch.zeros(1), p4=torch.zeros(1), heatmap=heat, center=center, regress=zeros, offset=zeros)
    for soft in (False, True):
        free = net.keypoints(out, soft=soft)[0]
        assert torch.allclose(free[:, :2], torch.tensor([32.0, 32.0]))  # B, 8 cells of 4 px
        guide = torch.tensor([[13.0, 11.0, 0.9]] * 17)[None]  # A, roughly
        guided = net.keypoints(out, soft=soft, guide=guide)[0]
        assert torch.allclose(guided[:, :2], torch.tensor([12.0, 12.0]))
        weak = guide.clone()
        weak[..., 2] = 0.1  # under GUIDE_SCORE: MoveNet's own choice
        assert torch.allclose(net.keypoints(out, soft=soft, guide=weak), net.keypoints(out, soft=soft))
    kp = torch.rand(2, 17, 3) * 64
    mirrored = flip_coco(kp, 64.0)
    lw, rw = COCO_KEYPOINTS.index("left_wrist"), COCO_KEYPOINTS.index("right_wrist")
    assert torch.allclose(mirrored[:, rw, 0], 64.0 - kp[:, lw, 0]) and torch.equal(mirrored[:, rw, 1:], kp[:, lw, 1:])
    assert torch.allclose(flip_coco(mirrored, 64.0), kp)


def test_part_head_reads_the_stride4_map_at_each_keypoint_and_trains_over_a_fixed_backbone(model) -> None:
    from recovery.models.hmr import PartPool

    net = _hmr(model, head_input="keypoints+parts", train_blocks=0, hidden=32).train()
    assert net.parts is not None and net.encoder.out_features == 512 and net.parts.out_features == 17 * 64
    out = net(_astronaut(64).expand(2, -1, -1, -1))
    out.pose.square().sum().backward()
    assert all(p.grad is None for p in net.backbone.parameters())
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parts.parameters())
    # each keypoint's vector is the map where its heatmap peaks: one hot cell per keypoint reads that cell
    pool = PartPool(3, num_keypoints=2, width=4)
    p4 = torch.randn(1, 3, 5, 6)
    heat = torch.full((1, 2, 5, 6), -1e4)
    heat[0, 0, 1, 2] = heat[0, 1, 4, 5] = 0.0
    f = pool(p4, heat).view(2, 4)
    conv = pool.conv(p4)[0]
    assert torch.allclose(f[0], conv[:, 1, 2]) and torch.allclose(f[1], conv[:, 4, 5])


def test_image_dropout_drops_whole_images_in_training_only() -> None:
    from recovery.models.hmr import KeypointEncoder

    enc = KeypointEncoder(17, 8, image_features=16, image_dropout=0.5).train()
    torch.manual_seed(0)
    kp, img = torch.rand(64, 17, 3) * 32, torch.randn(64, 16)
    f = enc(kp, 32.0, img)[:, 8:]
    dropped = (f == 0).all(1)
    assert 16 < dropped.sum() < 48  # about half of 64
    enc.eval()
    assert torch.allclose(enc(kp, 32.0, img)[:, 8:], enc.image(img))


def test_last_blocks_train_and_the_rest_stays(model) -> None:
    net = _hmr(model, head_input="keypoints", train_blocks=2, hidden=32, pretrained=False).train()
    out = net(torch.rand(2, 3, 32, 32))
    (out.pose.square().sum() + out.cam.square().sum()).backward()
    b = net.backbone
    trained = {n for n, p in b.named_parameters() if p.grad is not None and p.grad.abs().sum() > 0}
    assert trained and all(n.split(".")[0] != "stem" for n in trained)
    assert not any(n.startswith(f"blocks.{i}.") for n in trained for i in range(len(b.blocks) - 2))
    assert any(n.startswith(f"blocks.{len(b.blocks) - 1}.") for n in trained)
    assert all(not p.requires_grad for p in b.blocks[0].parameters())


def test_movenet_head_settings_are_checked_and_old_networks_keep_their_hash() -> None:
    from recovery.config import ModelConfig, RecoveryConfig, load_config

    with pytest.raises(ValueError, match="needs a MoveNet backbone"):
        ModelConfig(backbone="efficientnet_lite0", head_input="keypoints")
    with pytest.raises(ValueError, match="head_input must be one of"):
        ModelConfig(backbone="movenet_lightning", head_input="heatmaps")
    with pytest.raises(ValueError, match="train_blocks > 0"):
        ModelConfig(backbone="resnet18", train_blocks=3)
    with pytest.raises(ValueError, match="task .mesh. does not use model.head_input; remove them"):
        RecoveryConfig(task="mesh", model=ModelConfig(backbone="movenet_lightning", head_input="keypoints"))
    # networks described before these settings keep their hash (values computed at a4b2525, before them),
    # so their checkpoints still resume and initialise runs
    cfg = load_config("configs/recovery/hmr_blsm_lite0.yaml")
    assert (
        cfg.model_hash() == "e2bf21368736ed1d"
        and load_config("configs/recovery/tiny.yaml").model_hash() == "fedb502731cb44db"
    )
    assert "head_input" not in cfg.to_dict()["model"]
    kp = RecoveryConfig(model=ModelConfig(backbone="movenet_lightning", head_input="keypoints"))
    assert kp.to_dict()["model"]["head_input"] == "keypoints" and kp.model_hash() != cfg.model_hash()


def test_tiny_movenet_run_trains_and_predicts(tmp_path, fake_root, train_cache) -> None:
    from recovery_helpers import train_config, write_config

    from recovery import trainer
    from recovery.config import load_config
    from recovery.predictor import load_predictor
    from recovery.train import train

    cfg = train_config(
        fake_root,
        train_cache,
        model={
            "backbone": "movenet_lightning",
            "pretrained": True,
            "hidden": 32,
            "head_input": "keypoints+pooled",
            "image_dropout": 0.3,
            "train_blocks": 0,
        },
        train={
            "steps": 2,
            "batch_size": 4,
            "val_every": 100,
            "checkpoint_every": 100,
            "log_every": 1,
            "device": "cpu",
        },
    )
    mp = pytest.MonkeyPatch()
    mp.setattr(trainer, "plot_curves", lambda *a, **k: None)
    try:
        assert (
            train(load_config(write_config(tmp_path / "c.yaml", cfg)), tmp_path / "run", log=lambda *a: None)
            == "done"
        )
    finally:
        mp.undo()
    pr = load_predictor(tmp_path / "run" / "last.pt")
    assert pr.model.head_input == "keypoints+pooled" and pr.crop == 32
    # the backbone stayed MoveNet's: a fixed backbone is not trained
    ref = build_backbone("movenet_lightning", pretrained=True).state_dict()
    got = pr.model.backbone.state_dict()
    assert all(torch.equal(got[k].float(), ref[k].float()) for k in ref)
    res = pr(
        torch.rand(2, 3, 32, 32), torch.eye(3).expand(2, 3, 3) * torch.tensor([40.0, 40.0, 1.0])[:, None]
    )
    assert torch.isfinite(res.vertices).all() and res.keypoints_2d.shape[0] == 2


def test_fit_brings_the_projection_onto_the_keypoints_and_keeps_unsure_people(model) -> None:
    from recovery.models.fit2d import FitSettings, fit_to_keypoints
    from recovery.models.hmr import HMROutput, predict_body
    from recovery.utils.geometry import UPRIGHT_FACING_CAMERA

    torch.manual_seed(0)
    b, crop = 3, 192
    ids = [model.keypoint_names.index(n) for n in COCO_KEYPOINTS]
    k = torch.tensor([[400.0, 0, 96], [0, 400.0, 96], [0, 0, 1]]).expand(b, 3, 3)
    nb, ns = model.num_bone_coeffs, model.num_shape_coeffs
    truth = HMROutput(
        pose=torch.randn(b, 47) * 0.5,
        orient=UPRIGHT_FACING_CAMERA.expand(b, 3, 3),
        bone=torch.zeros(b, nb),
        shape=torch.zeros(b, ns),
        cam=torch.tensor([[0.9, 0.0, 0.05]]).expand(b, 3),
        thetas=torch.zeros(1, b, 1),
    )
    target = predict_body(model, truth, k, crop, torch.tensor(ids)).keypoints_2d
    conf = torch.full((b, 17, 1), 0.9)
    conf[2] = 0.1  # a person MoveNet is unsure of: kept as predicted
    start = HMROutput(
        pose=truth.pose + 0.4 * torch.randn(b, 47),
        orient=truth.orient,
        bone=truth.bone,
        shape=truth.shape,
        cam=truth.cam + torch.tensor([0.05, 0.03, -0.02]),
        thetas=truth.thetas,
    )
    fitted = fit_to_keypoints(
        model, start, k, crop, torch.cat([target, conf], -1), ids, FitSettings(iterations=60)
    )
    err = lambda o: (
        (predict_body(model, o, k, crop, torch.tensor(ids)).keypoints_2d - target).norm(dim=-1).mean(-1)
    )  # noqa: E731
    before, after = err(start), err(fitted)
    assert (after[:2] < 0.5 * before[:2]).all(), (before, after)
    assert torch.equal(fitted.pose[2], start.pose[2]) and torch.equal(fitted.cam[2], start.cam[2])
    assert fitted.bone is start.bone and fitted.shape is start.shape
    assert (
        fit_to_keypoints(model, start, k, crop, torch.cat([target, conf], -1), ids, FitSettings(iterations=0))
        is start
    )


def test_which_blocks_train_does_not_make_another_network() -> None:
    from recovery.config import ModelConfig, RecoveryConfig

    a = RecoveryConfig(
        model=ModelConfig(backbone="movenet_lightning", head_input="keypoints", train_blocks=0)
    )
    b = RecoveryConfig(
        model=ModelConfig(backbone="movenet_lightning", head_input="keypoints", train_blocks=4)
    )
    c = RecoveryConfig(
        model=ModelConfig(backbone="movenet_lightning", head_input="keypoints+pooled", train_blocks=4)
    )
    assert a.model_hash() == b.model_hash() != c.model_hash()


def _experiment(name: str):
    """``experiments/transfer/NAME.py`` as a module (the folder on sys.path: the scripts import each other)."""
    import importlib.util
    import sys
    from pathlib import Path

    folder = Path(__file__).resolve().parents[2] / "experiments/transfer"
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))
    spec = importlib.util.spec_from_file_location(name, folder / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_movenet_rows_on_the_full_sets_change_the_training_data_alone(tmp_path) -> None:
    """``movenet_rows.py --data full``: each trained row's config is its own with data.train the
    training sets of ``make recovery-data`` (and the seated postures), and a continuation starts from
    the full runs' network, not the subsets'."""
    import dataclasses
    from pathlib import Path

    from recovery.config import load_config

    root = Path(__file__).resolve().parents[2]
    mod = _experiment("movenet_rows")
    train, _, _ = mod.DATA["full"]
    assert train[:3] == ["out/data/train_hdri", "out/data/train_sky", "out/data/train_mocap"]
    for name in ("kp_frozen", "thunder_kp_frozen", "kp_frozen_long"):
        old = load_config(root / mod.row_config(name, None, tmp_path))
        new = load_config(mod.row_config(name, train, tmp_path))
        assert new.data.train == tuple(train), name
        init = str(tmp_path / "runs/kp_frozen/last.pt") if name == "kp_frozen_long" else ""
        assert new.train.init == init, name
        same = dataclasses.replace(new, data=dataclasses.replace(new.data, train=old.data.train),
                                   train=dataclasses.replace(new.train, init=old.train.init))
        assert same == old, name


def test_packaged_recipe_is_the_full_sets_rows(tmp_path) -> None:
    """The configs of ``make recovery-model`` (configs/recovery/hmr_blsm_movenet{,_long}.yaml) are those
    ``movenet_rows.py --data full`` writes for kp_frozen and kp_frozen_long, trained into the same folders,
    so the packaged network is the measured row (``recovery train --resume`` checks the config)."""
    import dataclasses
    from pathlib import Path

    from recovery.config import load_config

    root = Path(__file__).resolve().parents[2]
    mod = _experiment("movenet_rows")
    train, out, _ = mod.DATA["full"]
    make = (root / "Makefile").read_text().split("\nrecovery-model:")[1].split("\n\n")[0]
    for config, row in (("hmr_blsm_movenet", "kp_frozen"), ("hmr_blsm_movenet_long", "kp_frozen_long")):
        made = load_config(mod.row_config(row, train, tmp_path))
        if made.train.init:  # the continuation starts from the full runs' kp_frozen, as the ablation's does
            made = dataclasses.replace(made, train=dataclasses.replace(made.train, init=mod._from_root(out / "runs/kp_frozen/last.pt")))
        assert load_config(root / f"configs/recovery/{config}.yaml") == made, config
        assert f"train configs/recovery/{config}.yaml --out {mod._from_root(out / 'runs' / row)} --resume" in make, config


def test_movenet_table_puts_each_full_row_beside_its_subsets_row(tmp_path) -> None:
    """experiments/transfer/movenet_table.py: one line a row of the full sets, in movenet_rows.ROWS' order,
    each cell ``subsets -> full`` ("-" where the subsets lack the row), and --doc replaces only what stands
    between the markers."""

    mod = _experiment("movenet_table")

    def entry(pa, real, syn, ratio):
        return {"test": {"pa_mpjpe_mm": pa}, "transfer": {
            "real_pck@0.1": {"ours": real}, "synthetic_pck@0.1": {"ours": syn}, "ratio@0.1": ratio,
            "ratio_90": [ratio - 0.4, ratio + 0.4], "extent_ratio_real": [1.0, 1.02]}}

    full = {"kp_frozen_long": entry(99.2, 0.638, 0.8, 0.33), "kp_frozen": entry(106.5, 0.619, 0.781, 0.26),
            "thunder_kp_frozen_fit30": entry(85.0, 0.79, 0.88, 0.8)}
    subsets = {"kp_frozen": entry(110.5, 0.632, 0.773, 0.35), "ceiling_lightning": entry(None, 0.834, 0.876, 0.92),
               "ceiling_thunder": entry(None, 0.856, 0.897, 0.9)}
    lines = mod.table(subsets, full).splitlines()[2:]
    assert [ln.split("|")[1].strip() for ln in lines] == ["`kp_frozen`", "`kp_frozen_long`", "`thunder_kp_frozen_fit30`"]
    assert "| 110.5 -> **106.5** | 63.2 -> **61.9** | 77.3 -> **78.1** | 0.35 -> **0.26** | -0.14 to 0.66 |" in lines[0]
    assert "| - -> **99.2** |" in lines[1] and lines[1].endswith("| 1.00, 1.02 | not run | 19.6 (of 83.4 %) |")
    assert lines[0].endswith("| 21.5 (of 83.4 %) |") and lines[2].endswith("| 6.6 (of 85.6 %) |")  # each its own MoveNet
    assert mod.table({}, full).splitlines()[2].endswith("| not run | no ceiling row |")

    doc = tmp_path / "doc.md"
    doc.write_text(f"before\n{mod.MARK[0]}\nold table\n{mod.MARK[1]}\nafter\n")
    (tmp_path / "s.json").write_text(json.dumps({}))
    (tmp_path / "f.json").write_text(json.dumps(full))
    mod.SUBSETS, mod.FULL = tmp_path / "s.json", tmp_path / "f.json"
    assert mod.main(["--doc", str(doc)]) == 0
    got = doc.read_text()
    assert got.startswith(f"before\n{mod.MARK[0]}\n| row |") and got.endswith(f"|\n{mod.MARK[1]}\nafter\n")
    assert "old table" not in got and got.count("`kp_frozen") == 2
    (tmp_path / "bare.md").write_text("no markers\n")
    assert mod.main(["--doc", str(tmp_path / "bare.md")]) == 2
    assert (tmp_path / "bare.md").read_text() == "no markers\n"


def test_movenet_rows_share_one_budget_and_data() -> None:
    """Every trained row of experiments/transfer/movenet_rows.py has a config that parses, 800 steps of 32 on one
    data set and one validation set (docs/transfer.md, "A backbone that reads people in photographs");
    the one continuation (kp_frozen_long) starts from kp_frozen's network."""
    from pathlib import Path

    from recovery.config import load_config

    root = Path(__file__).resolve().parents[2]
    mod = _experiment("movenet_rows")
    trained = [n for n, (_, src) in mod.ROWS.items() if src == "config"]
    assert {"kp_frozen", "kpimg_frozen", "pooled_frozen"} <= set(trained)
    ref = load_config(root / "configs/recovery/movenet/kp_frozen.yaml")
    for name in trained:
        cfg = load_config(root / f"configs/recovery/movenet/{name}.yaml")
        assert (cfg.train.steps, cfg.train.batch_size) == (800, 32), name
        assert (cfg.data.train, cfg.data.val, cfg.data.effects) == (
            ref.data.train,
            ref.data.val,
            ref.data.effects,
        ), name
        assert cfg.model.backbone.startswith("movenet_"), name
        assert cfg.train.init == ("out/movenet/runs/kp_frozen/last.pt" if name == "kp_frozen_long" else ""), (
            name
        )
