"""``blsm train CONFIG --out MODEL``: population, registration, learning and evaluation in one run."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

import blsm
from blsm.cli import main
from blsm.learn.pipeline import load_config

SMALL = "configs/blsm/train_small.yaml"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """The small config, its work folder moved into a temporary folder."""
    from pathlib import Path

    root = tmp_path_factory.mktemp("train")
    cfg = yaml.safe_load((Path(__file__).parents[2] / SMALL).read_text())
    cfg["run"]["work"] = str(root / "work")
    path = root / "small.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = root / "model.npz"
    assert main(["train", str(path), "--out", str(out)]) == 0
    return path, out, root


def test_small_run_writes_a_loadable_model_and_a_report(run):
    _, out, root = run
    model = blsm.load(out)
    assert model.num_vertices == blsm.load().num_vertices
    assert model.num_shape_coeffs == 4 and model.num_bone_coeffs == 4
    w = model.weights
    assert torch_allclose(w.sum(1), 1.0) and float(w.min()) >= 0.0
    report = json.loads(out.with_suffix(".report.json").read_text())
    assert 0.9 < report["bone_pca_explained_first3"] <= 1.0
    reg = report["registration"]
    # Registration against ground-truth correspondence, on train and held-out scans.
    assert set(reg) == {"train", "test"}
    for split in reg.values():
        assert 0.5 < split["error_mean_mm"] < 15.0
        assert split["error_mean_mm"] < split["stage1_error_mean_mm"]
    ev = (root / "model_evaluation.md").read_text()
    assert "BLSM-linear" in ev and "SMPL-reimpl" in ev and "Registration error" in ev
    assert (root / "figures" / "model_evaluation_shape.png").stat().st_size > 1000
    import torch

    body = model(shape=torch.ones(1, 4), bone=torch.ones(1, 4))
    assert body.vertices.shape == (1, model.num_vertices, 3) and torch.isfinite(body.vertices).all()


def torch_allclose(x, v) -> bool:
    return bool((x - v).abs().max() < 1e-5)


def test_a_second_run_reuses_the_population_and_registrations(run, capsys):
    path, out, root = run
    regs = sorted((root / "work" / "round1" / "registrations").glob("*.npz"))
    stamp = {p.name: p.stat().st_mtime_ns for p in regs}
    cfg = yaml.safe_load(path.read_text())
    cfg["evaluation"]["enabled"] = False
    again = root / "again.yaml"
    again.write_text(yaml.safe_dump(cfg))
    assert main(["train", str(again), "--out", str(root / "model2.npz")]) == 0
    err = capsys.readouterr().err
    assert main(["train", str(again), "--out", str(root / "model2.npz")]) == 2  # never replaced silently
    assert "model2.npz: exists; pass --overwrite" in capsys.readouterr().err
    assert f"registration: {len(regs)} of {len(regs)} scans already registered" in err
    assert {p.name: p.stat().st_mtime_ns for p in regs} == stamp


def test_other_population_settings_in_the_same_work_folder_are_refused(run, capsys):
    path, _, root = run
    cfg = yaml.safe_load(path.read_text())
    cfg["population"]["subjects"] = 17
    other = root / "other.yaml"
    other.write_text(yaml.safe_dump(cfg))
    assert main(["train", str(other), "--out", str(root / "m3.npz")]) == 2
    err = capsys.readouterr().err.strip()
    assert "population made with other settings" in err and "\n" not in err
    assert not (root / "m3.npz").exists()
    cfg = yaml.safe_load(path.read_text())
    cfg["registration"]["iterations"] = 41  # same population, other registration settings
    other.write_text(yaml.safe_dump(cfg))
    assert main(["train", str(other), "--out", str(root / "m3.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]  # after the progress lines
    assert err.startswith("blsm train: error:") and "registrations made with other settings or another model" in err
    # The population is made with the initial rig (its template is the ground truth's): another rig
    # is another population.
    from blsm import io
    from blsm.model import DEFAULT_RIG

    rig = io.read_model(DEFAULT_RIG)
    rig.arrays["template"] = rig.arrays["template"] + np.float32(0.001)
    io.save_model(rig, root / "moved_rig.npz")
    assert main(["train", str(path), "--out", str(root / "m3.npz"), "--model", str(root / "moved_rig.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "population made with other settings" in err and not (root / "m3.npz").exists()


def test_config_errors_are_one_line_naming_file_and_key(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("population: {subjects: 10, colour: red}\n")
    with pytest.raises(ValueError, match=r"bad\.yaml: population\.colour: unknown key"):
        load_config(bad)
    bad.write_text("run: {rounds: 0}\n")
    assert main(["train", str(bad), "--out", str(tmp_path / "m.npz")]) == 2
    err = capsys.readouterr().err.strip()
    assert "rounds must be >= 1" in err and "\n" not in err
    bad.write_text("train: {shape: {num_coeffs: four}}\n")
    with pytest.raises(ValueError, match=r"train\.shape\.num_coeffs: expected an integer"):
        load_config(bad)
    load_config("configs/blsm/train_default.yaml")  # the shipped configs parse
    load_config(SMALL)


def test_a_malformed_scan_stops_the_run_before_any_registration(tmp_path, capsys):
    from blsm.learn.scans.population import make_population

    pop = tmp_path / "pop"
    make_population(pop, 3, seed=2, test_fraction=0.0)
    bad = sorted((pop / "scans").glob("*.npz"))[-1]
    with np.load(bad, allow_pickle=False) as z:
        arrays = dict(z)
    arrays["vertices"][5] = np.nan  # a damaged file (save_scan itself refuses to write one)
    np.savez(bad, **arrays)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"run: {{work: {tmp_path / 'w'}, workers: 1}}\npopulation: {{folder: {pop}}}\n")
    assert main(["train", str(cfg), "--out", str(tmp_path / "m.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert bad.name in err and "NaN" in err
    assert not list((tmp_path / "w").rglob("registrations/*.npz"))


def test_failed_registrations_are_left_out_of_the_learning(run, capsys):
    path, _, root = run
    n = len(list((root / "work" / "round1" / "registrations").glob("*.npz")))
    report = json.loads((root / "model.report.json").read_text())
    assert report["failed_registrations"] == {}  # none failed in the small run
    cfg = yaml.safe_load(path.read_text())
    cfg["run"]["max_landmark_rms_mm"] = 1.0  # below any landmark fit: every registration "failed"
    cfg["evaluation"]["enabled"] = False
    strict = root / "strict.yaml"
    strict.write_text(yaml.safe_dump(cfg))
    assert main(["train", str(strict), "--out", str(root / "m4.npz")]) == 2
    err = capsys.readouterr().err
    assert f"leaving out {n} failed registrations" in err
    assert not (root / "m4.npz").exists()
