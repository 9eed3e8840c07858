"""The ``recovery`` command: ``predict`` on a small image, and bad input (missing or empty dataset,
corrupt or foreign checkpoint, another config) as one line naming the file with exit status 2,
leaving a run folder as it was."""

from __future__ import annotations

import filecmp
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from recovery_helpers import train_config, write_config

from recovery.cli import main
from synth.dataset.shards import ShardWriter, SkipSample

W, H = 40, 48  # the test image, pixels


def _error(capsys, argv: list[str], *needles: str) -> str:
    """Run ``recovery argv``; it must fail with status 2 and one stderr line naming ``needles``."""
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("recovery: error: ")
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def _snapshot(folder: Path) -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in folder.iterdir()}


def _edit_checkpoint(src: Path, dst: Path, edit) -> Path:
    ck = torch.load(src, map_location="cpu", weights_only=False)
    edit(ck)
    torch.save(ck, dst)
    return dst


@pytest.fixture(scope="module")
def image(tmp_path_factory) -> Path:
    from PIL import Image

    path = tmp_path_factory.mktemp("recovery_image") / "person.png"
    rgb = np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(path)
    return path


@pytest.fixture(scope="module")
def empty_dataset(tmp_path_factory) -> Path:
    """A complete dataset without samples: every one was skipped."""

    def nobody(index, rng):
        raise SkipSample("nobody in view")

    out = tmp_path_factory.mktemp("recovery_empty") / "ds"
    ShardWriter(out=out, num=2, shard_size=2, seed=0).run(nobody)
    return out


@pytest.fixture
def run_copy(run_a, tmp_path) -> Path:
    """A copy of the finished tiny run (without best.pt), to resume with bad input."""
    dst = tmp_path / "run"
    shutil.copytree(run_a, dst, ignore=shutil.ignore_patterns("best.pt"))
    return dst


def _config(run_a: Path) -> Path:
    return run_a.parent / "config.yaml"


# -- predict


def test_predict_writes_parameters_mesh_and_overlay(run_a, image, model, tmp_path, capsys):
    out = tmp_path / "pred"
    assert main(["predict", str(run_a / "last.pt"), str(image), "--out", str(out), "--whole"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["mesh.obj", "overlay.png", "params.json"]
    p = json.loads((out / "params.json").read_text())
    angles = torch.tensor(p["angles"])
    assert len(p["pose"]) == 47 and angles.shape == (47,)
    lim = model.dof_limits
    assert ((angles >= lim[:, 0] - 1e-6) & (angles <= lim[:, 1] + 1e-6)).all()
    assert len(p["bone"]) == model.num_bone_coeffs and len(p["shape"]) == model.num_shape_coeffs
    assert p["transl"][2] > 0  # in front of the camera
    assert p["K"] == [[48.0, 0.0, 20.0], [0.0, 48.0, 24.0], [0.0, 0.0, 1.0]]  # f: the longer side
    assert p["crop"] == {"center": [20.0, 24.0], "side": 48.0, "size": 32}
    assert len(p["keypoints_3d_cam"]) == len(model.keypoint_names) == len(p["keypoint_names"])
    lines = (out / "mesh.obj").read_text().splitlines()
    verts = [ln for ln in lines if ln.startswith("v ")]
    assert len(verts) == model.num_vertices == 7002
    assert sum(ln.startswith("f ") for ln in lines) == model.faces.shape[0]
    v = np.array([[float(x) for x in ln.split()[1:]] for ln in verts])
    assert np.allclose(v.mean(0), p["transl"], atol=0.5)  # the body around its pelvis, camera frame
    from PIL import Image

    with Image.open(out / "overlay.png") as im:
        assert im.size == (3 * W, H)  # image | mesh | parts


def test_predict_with_a_box(run_a, image, tmp_path):
    out = tmp_path / "pred"
    assert (
        main(
            [
                "predict",
                str(run_a / "last.pt"),
                str(image),
                "--out",
                str(out),
                "--box",
                "5",
                "4",
                "25",
                "44",
                "--focal",
                "60",
            ]
        )
        == 0
    )
    p = json.loads((out / "params.json").read_text())
    assert p["crop"]["center"] == [15.0, 24.0] and p["crop"]["side"] == pytest.approx(48.0)
    assert p["K"][0][0] == 60.0 and p["box"] == [5.0, 4.0, 25.0, 44.0]


@pytest.mark.parametrize("box", [["0", "0", "50", "10"], ["-1", "0", "10", "10"], ["10", "10", "5", "20"]])
def test_predict_box_outside_the_image(run_a, image, tmp_path, capsys, box):
    out = tmp_path / "pred"
    _error(
        capsys,
        ["predict", str(run_a / "last.pt"), str(image), "--out", str(out), "--box", *box],
        "--box",
        str(image),
    )
    assert not out.exists()


def test_predict_bad_image(run_a, tmp_path, capsys):
    _error(
        capsys,
        ["predict", str(run_a / "last.pt"), str(tmp_path / "no.png"), "--out", str(tmp_path / "o")],
        f"{tmp_path / 'no.png'}: no such image",
    )
    _error(
        capsys,
        ["predict", str(run_a / "last.pt"), str(tmp_path / "no.png"), "--out", str(tmp_path / "o"), "--whole"],
        f"{tmp_path / 'no.png'}: no such image",
    )
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not a png")
    _error(
        capsys,
        ["predict", str(run_a / "last.pt"), str(bad), "--out", str(tmp_path / "o")],
        f"{bad}: not a readable image",
    )


# -- missing and empty datasets


def test_train_on_a_missing_dataset(fake_root, train_cache, tmp_path, capsys):
    missing = tmp_path / "nowhere"
    cfg = write_config(
        tmp_path / "c.yaml", train_config(fake_root, train_cache, data={"train": [str(missing)]})
    )
    out = tmp_path / "run"
    _error(capsys, ["train", str(cfg), "--out", str(out)], f"{missing}: no such dataset folder")
    assert not out.exists()
    cfg = write_config(tmp_path / "c.yaml", train_config(fake_root, train_cache, data={"val": str(missing)}))
    _error(capsys, ["train", str(cfg), "--out", str(out)], f"{missing}: no such dataset folder")
    assert not out.exists()


def test_train_on_an_empty_dataset(fake_root, empty_dataset, tmp_path, capsys):
    cfg = write_config(
        tmp_path / "c.yaml", train_config(fake_root, tmp_path / "cache", data={"train": [str(empty_dataset)]})
    )
    out = tmp_path / "run"
    _error(capsys, ["train", str(cfg), "--out", str(out)], f"{empty_dataset}: the dataset holds no samples")
    assert not out.exists()
    assert not any((tmp_path / "cache").glob("*/meta.json"))  # no cache either
    # A folder that is no dataset at all.
    cfg = write_config(
        tmp_path / "c.yaml", train_config(fake_root, tmp_path / "cache", data={"train": [str(tmp_path)]})
    )
    _error(
        capsys, ["train", str(cfg), "--out", str(out)], f"{tmp_path / 'manifest.json'}: no dataset manifest"
    )
    assert not out.exists()


def test_evaluate_on_a_missing_or_empty_dataset(run_a, empty_dataset, tmp_path, capsys):
    out = tmp_path / "eval"
    ck = str(run_a / "last.pt")
    _error(capsys, ["evaluate", ck, str(tmp_path / "nowhere"), "--out", str(out)], str(tmp_path / "nowhere"))
    _error(
        capsys,
        ["evaluate", ck, str(empty_dataset), "--out", str(out)],
        f"{empty_dataset}: the dataset holds no samples",
    )
    assert not out.exists()


# -- checkpoints: missing, corrupt, foreign model file, another config


def test_corrupt_checkpoints(run_a, fake_root, image, tmp_path, capsys):
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"\x80\x04 this is not a checkpoint" * 10)
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes((run_a / "last.pt").read_bytes()[: 1 << 20])
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(2)}, other)
    code = tmp_path / "code.pt"  # unpickling would call a function: refused, never run
    marker = tmp_path / "ran"
    torch.save({"format": "recovery-checkpoint", "x": _Runs(str(marker))}, code)
    out = tmp_path / "o"
    for path, why in (
        (code, "refused: loading it would run code"),
        (garbage, "corrupt checkpoint"),
        (truncated, "corrupt checkpoint"),
        (other, "not a 'recovery-checkpoint' file"),
        (tmp_path / "none.pt", "no such checkpoint"),
    ):
        _error(capsys, ["evaluate", str(path), str(fake_root), "--out", str(out)], f"{path}: {why}")
        _error(capsys, ["predict", str(path), str(image), "--out", str(out)], f"{path}: {why}")
        _error(capsys, ["export", str(path), "--out", str(tmp_path / "e.pt")], f"{path}: {why}")
    assert not out.exists() and not (tmp_path / "e.pt").exists() and not marker.exists()


class _Runs:
    """Pickles as a call of ``pathlib.Path.touch`` (what a malicious checkpoint could do)."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __reduce__(self):
        return (Path.touch, (Path(self.path),))


def test_resume_from_a_corrupt_checkpoint(run_copy, run_a, capsys):
    last = run_copy / "last.pt"
    last.write_bytes(last.read_bytes()[: 1 << 20])
    before = _snapshot(run_copy)
    _error(
        capsys,
        ["train", str(_config(run_a)), "--out", str(run_copy), "--resume"],
        f"{last}: corrupt checkpoint",
    )
    assert _snapshot(run_copy) == before


def test_checkpoint_of_another_model_file(run_a, fake_root, image, tmp_path, capsys):
    from recovery.predictor import export

    # Edited copies of the run's weights (the inference-only export: a sixth of last.pt's size).
    small = export(run_a / "last.pt", tmp_path / "small.pt")
    foreign = _edit_checkpoint(
        small, tmp_path / "foreign.pt", lambda ck: ck.update(blsm_model_sha256="0" * 64)
    )
    out = tmp_path / "o"
    for cmd in (["evaluate", str(foreign), str(fake_root)], ["predict", str(foreign), str(image)]):
        _error(capsys, [*cmd, "--out", str(out)], str(foreign), "another BLSM model file")
    # A config naming another model file (the rig the packaged model was learnt from) ...
    import blsm

    rig = Path(blsm.__file__).parent / "data" / "blsm_anny_rig.npz"
    moved = _edit_checkpoint(
        small, tmp_path / "moved.pt", lambda ck: ck["config"]["model"].update(blsm_model=str(rig))
    )
    line = _error(capsys, ["evaluate", str(moved), str(fake_root), "--out", str(out)], str(moved), str(rig))
    assert "another BLSM model file" in line
    # ... or a missing one.
    gone = tmp_path / "gone.npz"
    lost = _edit_checkpoint(
        small, tmp_path / "lost.pt", lambda ck: ck["config"]["model"].update(blsm_model=str(gone))
    )
    _error(
        capsys,
        ["predict", str(lost), str(image), "--out", str(out)],
        f"{gone}: the BLSM model file",
        str(lost),
    )
    assert not out.exists()


def test_resume_a_checkpoint_of_another_model_file(run_copy, run_a, capsys):
    last = run_copy / "last.pt"
    _edit_checkpoint(last, last, lambda ck: ck.update(blsm_model_sha256="0" * 64))
    before = _snapshot(run_copy)
    log = (run_copy / "log.jsonl").read_text()
    _error(
        capsys,
        ["train", str(_config(run_a)), "--out", str(run_copy), "--resume"],
        f"{last}: made for another",
        "blsm_model_sha256",
    )
    assert _snapshot(run_copy) == before and (run_copy / "log.jsonl").read_text() == log


def test_resume_with_another_config(run_copy, run_a, fake_root, train_cache, tmp_path, capsys):
    cfg = write_config(tmp_path / "changed.yaml", train_config(fake_root, train_cache, optim={"lr": 1e-3}))
    before = _snapshot(run_copy)
    line = _error(
        capsys,
        ["train", str(cfg), "--out", str(run_copy), "--resume"],
        f"{run_copy / 'last.pt'}",
        "another config",
        "optim.lr",
    )
    assert "start a new run folder" in line
    assert _snapshot(run_copy) == before
    assert filecmp.cmp(run_copy / "last.pt", run_a / "last.pt", shallow=False)


def test_train_into_a_finished_run_without_resume(run_copy, run_a, capsys):
    before = _snapshot(run_copy)
    _error(
        capsys,
        ["train", str(_config(run_a)), "--out", str(run_copy)],
        f"{run_copy / 'last.pt'}: a run exists here",
    )
    assert _snapshot(run_copy) == before


def test_unknown_config_key(fake_root, train_cache, tmp_path, capsys):
    cfg = train_config(fake_root, train_cache)
    cfg["optim"]["learning_rate"] = 0.1
    path = write_config(tmp_path / "typo.yaml", cfg)
    _error(capsys, ["train", str(path), "--out", str(tmp_path / "run")], str(path), "learning_rate")
    assert not (tmp_path / "run").exists()



@pytest.mark.parametrize("case", ["unused_section", "unused_key", "unknown_backbone", "missing_init", "init_of_another_network"])
def test_a_config_the_task_cannot_use_is_refused_before_any_cache(fake_root, run_a, tmp_path, capsys, case):
    """A section or key the task does not read, a backbone nobody registered, a ``train.init`` that is
    missing or of another network: one line, exit 2, no run folder and no cache."""
    cfg = train_config(fake_root, tmp_path / "cache")
    want = {
        "unused_section": "task 'mesh' does not use discriminator",
        "unused_key": "task 'mesh' does not use train.frozen_bn",
        "unknown_backbone": "unknown backbone 'nopenet'; known: resnet18",
        "missing_init": str(tmp_path / "absent.pt"),
        "init_of_another_network": "train.init is not a checkpoint of this network",
    }[case]
    if case == "unused_section":
        cfg["task"], cfg["discriminator"] = "mesh", {"enabled": True, "lr": 0.5}
    elif case == "unused_key":
        cfg["task"], cfg["train"]["frozen_bn"] = "mesh", True
        cfg.pop("discriminator")
        cfg["model"] = {"backbone": "efficientnet_lite0", "pretrained": False}
    elif case == "unknown_backbone":
        cfg["model"]["backbone"] = "nopenet"
    elif case == "missing_init":
        cfg["train"]["init"] = str(tmp_path / "absent.pt")
    else:
        cfg["train"]["init"] = str(run_a / "best.pt")
        cfg["model"]["hidden"] = 48
    path = write_config(tmp_path / "c.yaml", cfg)
    out = tmp_path / "run"
    _error(capsys, ["train", str(path), "--out", str(out)], want)
    assert not out.exists() and not (tmp_path / "cache").exists()


# -- export and cache


def test_export_predicts_like_the_run(run_a, image, tmp_path, capsys):
    exported = tmp_path / "model.pt"
    assert main(["export", str(run_a / "last.pt"), "--out", str(exported)]) == 0
    assert exported.stat().st_size < 0.5 * (run_a / "last.pt").stat().st_size  # float16, no optimiser state
    for ck, out in ((run_a / "last.pt", tmp_path / "full"), (exported, tmp_path / "half")):
        assert main(["predict", str(ck), str(image), "--out", str(out), "--whole"]) == 0
    full, half = (json.loads((tmp_path / d / "params.json").read_text()) for d in ("full", "half"))
    assert np.allclose(full["angles"], half["angles"], atol=1e-2)
    assert np.allclose(full["transl"], half["transl"], rtol=1e-2)
    assert half["checkpoint"] == str(exported)


def test_cache_command(fake_root, tmp_path):
    assert main(["cache", str(fake_root), "--out", str(tmp_path / "c"), "--crop", "16"]) == 0
    meta = json.loads((tmp_path / "c" / "meta.json").read_text())
    assert meta["count"] == 9 and meta["side"] == 24 and meta["crop"] == 16
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c"]  # the temporary folder was renamed
