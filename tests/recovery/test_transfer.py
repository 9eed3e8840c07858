"""The transfer check (recovery/eval/transfer.py): the box rule, the mean-pose floor, the report's
structure and the ratio, with a stand-in reference (a script that puts one fixed pose into every
box it is given); the MediaPipe reference itself is exercised by ``make bench`` (docs/transfer.md)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from recovery_helpers import CONTEXT, CROP, train_config, write_config

from recovery import cli
from recovery.config import load_config
from recovery.eval.transfer import (
    COCO_NAMES,
    JOINT_BOX_GROWTH,
    MEDIAPIPE_INDEX,
    Domain,
    Person,
    hits,
    mean_pose_floor,
    person_boxes,
    read_boxes,
    summarise,
    visible_joints,
)

# A stand-in for blsm/pose2d/mediapipe_pose.py: the same interface (JOB.json OUT.json), one fixed pose
# (TEMPLATE, in box coordinates) placed into each box; nobody in a box narrower than 20 px; it
# counts its calls in CALLS so that the test can see the cache at work.
FAKE_REFERENCE = '''
import json, sys
from pathlib import Path
TEMPLATE = json.loads(Path(__file__).with_name("template.json").read_text())
job = json.loads(Path(sys.argv[1]).read_text())
calls = Path(__file__).with_name("CALLS")
calls.write_text(str(int(calls.read_text()) + 1 if calls.exists() else 1))
items = []
for it in job["items"]:
    x0, y0, x1, y1 = it["box"]
    if x1 - x0 < 20:
        items.append({"landmarks": None})
        continue
    lms = [[x0 + (x1 - x0) * u, y0 + (y1 - y0) * v, 0.9 if vis else 0.1] for u, v, vis in TEMPLATE]
    items.append({"landmarks": lms})
Path(sys.argv[2]).write_text(json.dumps({"reference": "fake", "items": items}))
'''


def _template() -> list[list[float]]:
    """33 landmarks in box coordinates: the 17 COCO ones on a stick figure, the rest hidden."""
    rng = np.random.default_rng(3)
    t = [[0.5, 0.5, 0] for _ in range(33)]
    for j, m in enumerate(MEDIAPIPE_INDEX):
        t[m] = [float(rng.uniform(0.2, 0.8)), 0.1 + 0.8 * j / 16, 1]
    return t


@pytest.fixture
def fake_reference(tmp_path) -> str:
    d = tmp_path / "ref"
    d.mkdir()
    (d / "template.json").write_text(json.dumps(_template()))
    (d / "fake_ref.py").write_text(FAKE_REFERENCE)
    return f"{sys.executable} {d / 'fake_ref.py'}"


@pytest.fixture
def real_folder(tmp_path) -> Path:
    d = tmp_path / "real"
    d.mkdir()
    rng = np.random.default_rng(0)
    for name in ("a.png", "b.jpg"):
        Image.fromarray(rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)).save(d / name)
    (d / "boxes.json").write_text(json.dumps({"a.png": [[10, 5, 70, 115], [100, 20, 110, 60]], "b.jpg": [[40, 10, 120, 110]]}))
    return d


def test_box_rule_and_floor_by_hand():
    # three people with the same pose in box coordinates, one with a joint moved: the floor is the
    # per-joint median (the common pose), exact for the first two, one joint off for the third
    k = len(COCO_NAMES)
    base = np.stack([np.linspace(0, 1, k), np.linspace(0, 2, k)], 1)
    ref = np.zeros((3, k, 3))
    for i, (scale, shift) in enumerate([(50, (10, 20)), (100, (200, 30)), (80, (5, 5))]):
        ref[i, :, :2] = base * scale + shift
    ref[..., 2] = 0.9
    ref[2, 4, :2] += 40  # person 2's right ear, 0.5 of its box away... but inside the joint box
    ref[1, 3, 2] = 0.2  # hidden: not counted, not in the box
    vis = visible_joints(ref, [(1000, 1000)] * 3)
    assert vis.sum() == 3 * k - 1
    centre, side, ok = person_boxes(ref, vis)
    assert ok.all()
    np.testing.assert_allclose(side[:2], JOINT_BOX_GROWTH * np.array([100, 200]))
    np.testing.assert_allclose(centre[0], [10 + 25, 20 + 50])
    floor = mean_pose_floor(ref, vis, centre, side, ok)
    np.testing.assert_allclose(floor[:2], ref[:2, :, :2], atol=1e-9)
    h = hits(floor, ref, vis, side, 0.1)
    assert h.tolist() == [k, k - 1, k - 1]  # person 2 misses its moved ear only
    # fewer than MIN_JOINTS visible: not scored
    ref[0, 5:, 2] = 0.0
    _, _, ok = person_boxes(ref, visible_joints(ref, [(1000, 1000)] * 3))
    assert ok.tolist() == [False, True, True]


def _domain(name: str, n: int, ours_hits: int, floor_hits: int) -> Domain:
    """``n`` people at a 100 px box, all 17 joints visible; the network's first ``ours_hits`` joints
    and the floor's first ``floor_hits`` on the reference, the others 50 px off."""
    k = len(COCO_NAMES)
    ref = np.zeros((n, k, 3))
    ref[..., 0], ref[..., 1], ref[..., 2] = np.arange(k) * 5.0, 10.0 + np.arange(k) * 2.0, 1.0
    ours, floor = ref[..., :2].copy(), ref[..., :2].copy()
    ours[:, ours_hits:, 0] += 50
    floor[:, floor_hits:, 0] += 50
    people = [Person(Path(f"{name}{i}.png"), (0, 0, 100, 100), (100, 100)) for i in range(n)]
    return Domain(name, people, ref, np.ones((n, k), bool), np.full((n, 2), 50.0), np.full(n, 100.0),
                  np.ones(n, bool), ours, floor)


def test_transfer_ratio_by_hand():
    # real: 10 vs 8 of 17 joints (gain 2/17); synthetic: 15 vs 7 (gain 8/17): ratio 0.25 at PCK@0.1;
    # the 50 px misses are within 0.2 x 100 px? no (50 > 20): the same at PCK@0.2
    rep = summarise(_domain("real", 4, 10, 8), _domain("synthetic", 6, 15, 7))
    k = len(COCO_NAMES)
    assert rep["domains"]["real"]["pck@0.1"]["ours"] == pytest.approx(10 / k)
    assert rep["domains"]["synthetic"]["pck@0.1"]["gain"] == pytest.approx(8 / k)
    assert rep["transfer_ratio@0.1"] == pytest.approx(0.25)
    assert rep["transfer_ratio@0.2"] == pytest.approx(0.25)
    # the network's joints span the reference's except the 50 px shifted ones: wider by 50 px of 80
    assert rep["domains"]["synthetic"]["extent_ratio"] == pytest.approx([130 / 80, 1.0])
    lo, hi = rep["transfer_ratio_90"]
    assert lo == pytest.approx(0.25) and hi == pytest.approx(0.25)  # identical people: no spread
    assert "transfer_ratio_synthetic_floor@0.1" not in rep
    # the second reading: the synthetic median pose as the floor on photographs, here 4 of 17 joints
    real = _domain("real", 4, 10, 8)
    real.synthetic_floor = real.ref[..., :2].copy()
    real.synthetic_floor[:, 4:, 0] += 50
    rep = summarise(real, _domain("synthetic", 6, 15, 7))
    assert rep["domains"]["real"]["pck@0.1"]["synthetic_floor"] == pytest.approx(4 / k)
    assert rep["transfer_ratio_synthetic_floor@0.1"] == pytest.approx((10 - 4) / 8)
    assert rep["transfer_ratio@0.1"] == pytest.approx(0.25)  # the first reading is unchanged


def test_transfer_report(fake_root, real_folder, fake_reference, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["transfer", "default", "--real", str(real_folder), "--synthetic", str(fake_root), "--out", str(out),
            "--reference-command", fake_reference, "--synthetic-people", "5"]
    assert cli.main(argv) == 0
    rep = json.loads((out / "report.json").read_text())
    real, syn = rep["domains"]["real"], rep["domains"]["synthetic"]
    assert (real["people"], real["images"], real["scored"], real["reference_failures"]) == (3, 2, 2, 1)
    assert syn["people"] == 5 and syn["scored"] + syn["reference_failures"] == 5
    for d in (real, syn):
        assert d["joints"] == d["scored"] * len(COCO_NAMES)
        for a in ("0.1", "0.2"):
            # every box holds the same pose: the floor reproduces the reference exactly
            assert d[f"pck@{a}"]["floor"] == 1.0
            assert 0.0 <= d[f"pck@{a}"]["ours"] <= 1.0
            assert d[f"pck@{a}"]["gain"] == pytest.approx(d[f"pck@{a}"]["ours"] - 1.0)
    assert "reference_vs_labels" in syn["pck@0.1"] and "reference_vs_labels" not in real["pck@0.1"]
    for d in (real, syn):
        assert len(d["extent_ratio"]) == 2 and all(v > 0 for v in d["extent_ratio"])
        assert set(d["per_joint@0.1"]) == set(COCO_NAMES)
        assert all(j["floor"] == 1.0 for j in d["per_joint@0.1"].values())
    # the synthetic median pose in the real boxes: the same pose, so the same hits as the floor
    assert real["pck@0.1"]["synthetic_floor"] == 1.0 and "synthetic_floor" not in syn["pck@0.1"]
    # no gain over the floor on synthetic images: no skill to transfer, the ratio is undefined
    assert np.isnan(rep["transfer_ratio@0.1"]) and rep["transfer_ratio_90"] is None
    assert np.isnan(rep["transfer_ratio_synthetic_floor@0.1"])
    assert rep["reference"] == ["fake"]
    for name in ("report.md", "sheet_real.png", "sheet_synthetic.png"):
        assert (out / name).is_file()
    assert "Transfer ratio" in capsys.readouterr().out
    calls = Path(fake_reference.split()[1]).with_name("CALLS")
    assert calls.read_text() == "2"  # one call per domain ...
    assert cli.main(argv) == 0
    assert calls.read_text() == "2"  # ... and none on a second run: the answers are cached


@pytest.mark.parametrize("content, problem", [
    (None, "no such file"),
    ("{not json", "not JSON"),
    ('{"a.png": [[10, 5, 700, 115]]}', "inside the 160 x 120 image"),
    ('{"missing.png": [[1, 1, 5, 5]]}', "no such image"),
    ('{"a.png": []}', "non-empty list"),
])
def test_bad_boxes(real_folder, fake_root, fake_reference, tmp_path, capsys, content, problem):
    boxes = real_folder / "boxes.json"
    if content is None:
        boxes.unlink()
    else:
        boxes.write_text(content)
    with pytest.raises(ValueError, match=problem):
        read_boxes(real_folder)
    out = tmp_path / "out"
    assert cli.main(["transfer", "default", "--real", str(real_folder), "--synthetic", str(fake_root), "--out", str(out),
                     "--reference-command", fake_reference]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and problem in err[0] and not out.exists()


def test_no_reference_environment(real_folder, fake_root, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("RECOVERY_REFERENCE_ENV", str(tmp_path / "nowhere"))
    assert cli.main(["transfer", "default", "--real", str(real_folder), "--synthetic", str(fake_root),
                     "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "setup_reference.sh" in err[0]


def test_ablation_rows_share_one_budget():
    """Every row of the transfer ablation (experiments/transfer/transfer_ablation.py) has a config that parses,
    and every row trains on one budget (docs/transfer.md, "The ablation"): 800 steps of 32 crops;
    the fine-tuning rows start from the 9000-step network at one rate and schedule. The GPU pair
    shares its own budget, the packaged network's 288k crops, from ImageNet."""
    root = Path(__file__).resolve().parents[2]
    path = root / "experiments/transfer/transfer_ablation.py"
    spec = importlib.util.spec_from_file_location("transfer_ablation", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    trained = {name: cfg for name, (_, _, cfg) in mod.ROWS.items() if cfg}
    assert len(trained) >= 10 and "base" in trained
    for name, config in trained.items():
        cfg = load_config(root / f"configs/recovery/transfer/{config}.yaml")
        if name in mod.GPU_ROWS:
            assert (cfg.train.steps * cfg.train.batch_size, cfg.train.init) == (288000, ""), name
            assert cfg.model.pretrained and cfg.model.backbone in ("efficientnet_lite0", "efficientnet_lite2"), name
            continue
        assert (cfg.train.steps, cfg.train.batch_size) == (800, 32), name
        if cfg.train.init:
            assert cfg.train.init == mod.BASE_WEIGHTS and cfg.optim.lr == 1e-4 and cfg.optim.warmup_steps == 50, name
        else:
            assert name.startswith("imagenet_") and cfg.model.pretrained, name


def test_gpu_carry_round_trip(tmp_path, model, fake_root):
    """experiments/transfer/gpu_carry.py: the crop caches of two configs' datasets travel, one of them
    as the first rows of the other (the same seed, fewer samples), and unpack on another root into
    caches that training accepts as they are (not rebuilt: only the manifests travel): parts, masks
    and labels exact, images within WebP's loss."""
    import shutil

    from fakes import make_dataset

    from recovery.datasets.cache import build_cache, cache_folder

    root = Path(__file__).resolve().parents[2]
    sys.path.insert(0, str(root))
    from experiments.transfer import gpu_carry

    here, there = tmp_path / "here", tmp_path / "there"
    shutil.copytree(fake_root, here / "data/big")  # 6 images
    make_dataset(here / "data/small", num=3, model=model)  # the same seed: its first 3 images
    names = []
    for name, data in (("a", "data/big"), ("b", "data/small")):
        cfg = train_config(Path(data), Path("out/gpu_cache"))
        cfg["data"]["val"] = ""
        for folder in (here, there):
            (folder / "configs").mkdir(parents=True, exist_ok=True)
            write_config(folder / f"configs/{name}.yaml", cfg)
        names.append(f"configs/{name}.yaml")
    gpu_carry.make_carry(tmp_path / "carry", names, "WEBP", 90, None, root=here)
    spec = json.loads((tmp_path / "carry/carry.json").read_text())
    by_path = {e["path"]: (name, e) for name, e in spec["datasets"].items()}
    big, small = by_path["data/big"], by_path["data/small"]
    assert big[1]["prefix_of"] is None and small[1]["prefix_of"] == big[0]
    assert not (tmp_path / "carry" / small[0] / "images.npz").exists()
    gpu_carry.unpack(tmp_path / "carry", root=there)

    def refuse(*a):
        raise AssertionError(f"the unpacked cache was rebuilt: {a}")

    for p in ("data/big", "data/small"):
        a = cache_folder(here / p, here / "out/cache", CROP, CONTEXT)
        b = cache_folder(there / p, there / "out/gpu_cache", CROP, CONTEXT)
        assert build_cache(there / p, b, CROP, CONTEXT, log=refuse) == b
        for arr in ("parts", "masks"):
            assert np.array_equal(np.load(a / f"{arr}.npy"), np.load(b / f"{arr}.npy")), (p, arr)
        la, lb = np.load(a / "labels.npz"), np.load(b / "labels.npz")
        assert sorted(la.files) == sorted(lb.files) and all(np.array_equal(la[k], lb[k]) for k in la.files)
        ia, ib = np.load(a / "images.npy").astype(float), np.load(b / "images.npy").astype(float)
        assert ia.shape == ib.shape and np.abs(ia - ib).mean() < 3.0, (p, np.abs(ia - ib).mean())


# The reference of the ceiling test: on astronaut.png, MoveNet Lightning's own keypoints on the whole
# photograph (tests/recovery/test_movenet.py's stored values, scaled to 512 px) as BlazePose landmarks;
# on every other image the stick figure of FAKE_REFERENCE.
CEILING_REFERENCE = FAKE_REFERENCE.replace('''    x0, y0, x1, y1 = it["box"]''', '''    x0, y0, x1, y1 = it["box"]
    if it["image"].endswith("astronaut.png"):
        items.append({"landmarks": json.loads(Path(__file__).with_name("astronaut.json").read_text())})
        continue''')


def test_ceiling_row_scores_movenet_itself(fake_root, tmp_path, capsys):
    """``recovery transfer movenet_lightning``: MoveNet's keypoints, cropped by the box rule and mapped
    back into the photograph, agree with MoveNet's keypoints on the whole photograph."""
    skimage_data = pytest.importorskip("skimage.data")
    from test_movenet import ASTRONAUT

    from recovery.models.backbones.movenet import COCO_KEYPOINTS

    real = tmp_path / "real"
    real.mkdir()
    Image.fromarray(skimage_data.astronaut()).save(real / "astronaut.png")
    (real / "boxes.json").write_text(json.dumps({"astronaut.png": [[20, 20, 400, 510]]}))
    d = tmp_path / "ref"
    d.mkdir()
    (d / "template.json").write_text(json.dumps(_template()))
    lms = [[0.0, 0.0, 0.0] for _ in range(33)]
    for name, m in zip(COCO_NAMES, MEDIAPIPE_INDEX, strict=True):
        x, y, s = ASTRONAUT["movenet_lightning"][COCO_KEYPOINTS.index(name)]
        lms[m] = [x * 512 / 192, y * 512 / 192, 0.9 if s > 0.3 else 0.1]
    (d / "astronaut.json").write_text(json.dumps(lms))
    (d / "ref.py").write_text(CEILING_REFERENCE)
    out = tmp_path / "out"
    assert cli.main(["transfer", "movenet_lightning", "--real", str(real), "--synthetic", str(fake_root), "--out", str(out),
                     "--reference-command", f"{sys.executable} {d / 'ref.py'}", "--synthetic-people", "3"]) == 0
    rep = json.loads((out / "report.json").read_text())
    r = rep["domains"]["real"]
    assert r["scored"] == 1 and r["joints"] >= 9
    assert r["pck@0.1"]["ours"] == 1.0  # the same network on a crop of the same photograph
    assert (out / "sheet_real.png").is_file() and (out / "sheet_synthetic.png").is_file()
    assert cli.main(["transfer", "movenet_lightning", "--real", str(real), "--synthetic", str(fake_root), "--out", str(out),
                     "--reference-command", f"{sys.executable} {d / 'ref.py'}", "--flip"]) == 2
    assert "--flip" in capsys.readouterr().err
