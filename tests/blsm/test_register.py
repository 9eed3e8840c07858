"""Tests of blsm/learn/registration/register.py (thesis Sec. 5.4.1, Eqs. 5.13-5.25): the whole registration,
its settings (blsm/learn/registration/register_config.py) and ``blsm register`` (blsm/learn/cli.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from synthetic_scans import synthetic_scan, write_scan_npz

from blsm.cli import main
from blsm.learn.posing import pose
from blsm.learn.registration.register import register
from blsm.learn.registration.register_config import DEFAULT_CONFIG, RegisterConfig, load_config
from blsm.learn.registration.registrations import correspondence_error, load_registration

pytestmark = pytest.mark.usefixtures("one_thread")


FAST = dict(stage1_iterations=150, iterations=60, scan_samples=20_000, model_samples=8_000, mnn_refresh=5)


@pytest.mark.parametrize("tangent_weight", [1.0, 0.0])
def test_register_reduces_error(model, gen, selection, tangent_weight):
    scan = synthetic_scan(model, gen, posed=False, selection=selection)
    cfg = load_config(DEFAULT_CONFIG)
    cfg = RegisterConfig(**{**cfg.__dict__, **FAST, "mnn_tangent_weight": tangent_weight})
    reg = register(model, [scan], cfg, selection=selection, progress=False)[0]
    m = reg.meta
    mean_mm, max_mm = correspondence_error(reg, scan.gt_points)
    assert mean_mm == pytest.approx(m["error_mean_mm"])
    assert mean_mm < 0.85 * m["stage1_error_mean_mm"]
    assert mean_mm < 7.0
    assert reg.vertices.shape == (model.num_vertices, 3) and reg.displacement.shape == (model.num_vertices, 3)
    # S^ = LBS(V_T + V_D, T(b, theta)) (Eq. 5.14's parametrisation).
    with torch.no_grad():
        again = pose(model, model.template + torch.as_tensor(reg.displacement), bone_scales=torch.as_tensor(reg.bone_scales)[None],
                     angles=torch.as_tensor(reg.angles)[None], global_orient=torch.as_tensor(reg.global_orient)[None],
                     transl=torch.as_tensor(reg.transl)[None]).vertices[0]
    np.testing.assert_allclose(again.numpy(), reg.vertices, atol=1e-5)


def test_config_file(tmp_path):
    good = tmp_path / "c.yaml"
    good.write_text("iterations: 7\nlr: 0.001\n")
    cfg = load_config(good)
    assert cfg.iterations == 7 and cfg.lr == 0.001
    bad = tmp_path / "b.yaml"
    bad.write_text("iteratons: 7\n")
    with pytest.raises(ValueError, match="b.yaml: iteratons: unknown key"):
        load_config(bad)
    bad.write_text("iterations: many\n")
    with pytest.raises(ValueError, match="expected an integer"):
        load_config(bad)
    assert load_config(DEFAULT_CONFIG).iterations > 0  # the shipped defaults parse
    bad.write_text("shape_init: 1\n")
    with pytest.raises(ValueError, match="expected true or false"):
        load_config(bad)


def test_shipped_config_equals_defaults():
    # One source of truth: the YAML `blsm register` reads and RegisterConfig() agree.
    assert load_config(DEFAULT_CONFIG) == RegisterConfig()


def _landmark_yaml(path: Path, names, idx) -> Path:
    path.write_text("".join(f"{n}: {{vertex: {int(i)}}}\n" for n, i in zip(names, idx)))
    return path


def test_cli(tmp_path, model, gen, selection, capsys):
    scan = synthetic_scan(model, gen, posed=True, selection=selection, holes=False)
    vidx = selection.vertices[:, 0].numpy()
    lm = _landmark_yaml(tmp_path / "lm.yaml", scan.landmark_names, vidx)
    cfg = tmp_path / "c.yaml"
    cfg.write_text("stage1_iterations: 20\nstage1_shape_iterations: 5\nsurface_rounds: 1\nsurface_iterations: 2\n"
                   "iterations: 3\nscan_samples: 2000\nmodel_samples: 1000\n")
    good = write_scan_npz(scan, tmp_path / "s1.npz")
    out = tmp_path / "out"
    args = [str(good), "--landmark-definitions", str(lm), "--out", str(out), "--config", str(cfg)]
    assert main(["register", *args]) == 0
    reg = load_registration(out / "s1.npz")
    assert reg.meta["scan"] == "posed" and reg.meta["iterations"] == 3
    capsys.readouterr()
    assert main(["register", *args]) == 2  # never overwrites silently
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists" in err[0]

    bad_v = scan.vertices.copy()
    bad_v[3] = np.nan
    cases = {
        "nan.npz": dict(vertices=bad_v),
        "empty.npz": dict(vertices=np.zeros((0, 3), np.float32), faces=np.zeros((0, 3), np.int32)),
        "nonmanifold.npz": dict(faces=np.concatenate([scan.faces, scan.faces[:1], scan.faces[:1]])),
        "nolm.npz": dict(landmarks=np.full_like(scan.landmarks, np.nan)),
    }
    for name, override in cases.items():
        p = write_scan_npz(scan, tmp_path / name, **override)
        assert main(["register", str(p), "--landmark-definitions", str(lm), "--out", str(out), "--config", str(cfg)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and name in err[0], (name, err)
    # A user's mesh with its located landmarks in a JSON file (--landmarks), e.g. from a scanner.
    import json

    import trimesh

    mesh = tmp_path / "user_scan.obj"
    trimesh.Trimesh(scan.vertices, scan.faces, process=False).export(mesh)
    lm_json = tmp_path / "user_scan_landmarks.json"
    lm_json.write_text(json.dumps({n: [float(c) for c in x] for n, x in zip(scan.landmark_names, scan.landmarks)}))
    assert main(["register", str(mesh), "--landmarks", str(lm_json), "--out", str(out), "--config", str(cfg)]) == 0
    assert load_registration(out / "user_scan.npz").vertices.shape == (model.num_vertices, 3)
    assert main(["register", str(mesh), str(good), "--landmarks", str(lm_json), "--out", str(tmp_path / "o2")]) == 2
    assert "one scan" in capsys.readouterr().err
    assert main(["register", str(mesh), "--out", str(tmp_path / "o3"), "--config", str(cfg)]) == 2  # no landmarks
    assert "user_scan" in capsys.readouterr().err
    (tmp_path / "junk.npz").write_text("not a zip")
    assert main(["register", str(tmp_path / "junk.npz"), "--landmark-definitions", str(lm), "--out", str(out)]) == 2
    assert "junk.npz" in capsys.readouterr().err


def test_population_scan_registers(model, selection, tmp_path):
    """A real Anny population scan (noise, holes, 5 mm landmark noise) against its ground truth."""
    pytest.importorskip("anny")
    from blsm.learn.scans.format import load_scan
    from blsm.learn.scans.population import make_population, read_population

    # The population is made with the packaged rig (its template defines the ground truth).
    make_population(out=tmp_path / "pop", n_subjects=1, posed_subjects=1, poses_per_subject=1, seed=3,
                    test_fraction=0.0)
    index = read_population(tmp_path / "pop")
    scan = load_scan(tmp_path / "pop" / index["subjects"][0]["scans"][1])  # the posed scan
    reg = register(model, [scan], RegisterConfig(), selection=selection, progress=False)[0]
    m = reg.meta
    # Measured 4.4-5.4 mm mean on such scans (the thesis-only pipeline: 5-6 mm); the target of
    # 3 mm is not reached (see the module docstring).
    assert m["error_mean_mm"] < 6.5
    assert m["error_mean_mm"] < m["stage1_error_mean_mm"]
    # The shape-space landmark fit beats the skeleton-only floor (about 12 mm on Anny bodies).
    assert m["surface_fit_landmark_rms_mm"] < 11.0
