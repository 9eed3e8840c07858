"""experiments/recovery_ablation/ablation.py (thesis Table 4.3): the whole run at toy scale (two steps
per run) on the fake dataset — every stage runs, the JSON has the promised keys, and a second call
reuses what is done."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from recovery_helpers import CROP, one_thread

TINY_MESH = {"channels": [4, 4, 4, 4], "latent": 8, "hidden": 16}


def _library(folder, names, model):
    from blsm.mocap.library import MotionClip, save_clip

    t = 4
    rng = np.random.default_rng(0)
    for name in names:
        x = rng.normal(size=(t, model.num_dofs)).astype(np.float32) * 0.3
        z3, z1 = np.zeros((t, 3), np.float32), np.zeros(t, np.float32)
        save_clip(MotionClip(name, 30.0, x, z3, z3, z1, z1, z1, np.zeros((t, 0), np.float32),
                             meta={"dof_names": list(model.dof_names), "segments": []}), folder / f"{name}.npz")


def test_ablation_end_to_end(tmp_path, fake_root, train_cache, mesh_cache, model, monkeypatch):
    from experiments.recovery_ablation.ablation import CONFIGS, run_ablation
    from recovery import trainer

    monkeypatch.setattr(trainer, "plot_curves", lambda *a, **k: None)
    _library(tmp_path / "test_lib", ["007_12", "005_20"], model)
    cfgs = tmp_path / "cfg"
    cfgs.mkdir()
    train = {"steps": 2, "batch_size": 2, "val_every": 2, "checkpoint_every": 2, "log_every": 1, "device": "cpu"}
    meshes = {"library": "", "test_library": str(tmp_path / "test_lib"), "stats_meshes": 32, "val_meshes": 4,
              "test_meshes": 8, "pca_meshes": 16, "pca_components": 4}
    data = {"train": [str(fake_root)], "val": str(fake_root), "crop": CROP, "cache": str(train_cache), "workers": 0}
    ae_path = str(tmp_path / "runs" / "autoencoder" / "last.pt")
    mesh = {**TINY_MESH, "cache": str(mesh_cache)}
    model_cfg = {"backbone": "efficientnet_lite0", "pretrained": False}  # the mesh network's hidden is mesh.hidden
    hmr_cfg = {**model_cfg, "hidden": 16}
    configs = {
        "autoencoder": {"task": "autoencoder", "mesh": mesh, "meshes": meshes, "train": train},
        "A": {"task": "hmr_blsm", "model": {**hmr_cfg, "ief_iterations": 1}, "data": data, "discriminator": {"enabled": False}, "train": train},
        "B": {"task": "hmr_blsm", "model": hmr_cfg, "data": data, "discriminator": {"prior_samples": 64}, "train": train},
        "C": {"task": "mesh", "model": model_cfg, "data": data, "mesh": mesh, "meshes": meshes, "train": train},
        "D": {"task": "mesh", "model": model_cfg, "data": data, "mesh": {**mesh, "autoencoder": ae_path, "freeze_decoder": True}, "meshes": meshes, "train": train},
        "E": {"task": "mesh", "model": model_cfg, "data": data, "mesh": mesh, "began": {"enabled": True}, "meshes": meshes, "train": train},
        "F": {"task": "mesh", "model": model_cfg, "data": data, "mesh": {**mesh, "autoencoder": ae_path, "freeze_decoder": True},
              "began": {"enabled": True, "pretrained": True, "freeze": True}, "meshes": meshes, "train": train},
    }
    for name, c in configs.items():
        (cfgs / f"{name}.yaml").write_text(yaml.safe_dump(c))
    logs: list[str] = []
    with one_thread():
        res = run_ablation(cfgs, fake_root, tmp_path / "runs", tmp_path / "docs", log=logs.append)
    saved = json.loads((tmp_path / "docs" / "figures" / "recovery_ablation.json").read_text())
    assert set(saved["configs"]) == set(CONFIGS)
    for c in saved["configs"].values():
        assert {"joint_mm", "vertex_mm", "pa_joint_mm"} <= set(c) and c["vertex_mm"] > 0
    ae = saved["autoencoder"]
    assert {"vertex_mm", "pca_vertex_mm", "prior_vertex_mm", "prior_pca_vertex_mm"} <= set(ae) and ae["test_meshes"] == 8
    assert ae["pca_by_components"]["4"][0] == pytest.approx(ae["pca_vertex_mm"])  # the full model's point of the curve
    for png in ("recovery_ablation_C_vs_A.png", "recovery_ablation_E_vs_B.png", "recovery_ablation_roughness.png"):
        assert (tmp_path / "docs" / "figures" / png).stat().st_size > 1000
    assert "does not hold" in (tmp_path / "docs" / "recovery_ablation.md").read_text() or "holds" in (tmp_path / "docs" / "recovery_ablation.md").read_text()
    # a second call trains and evaluates nothing again, and takes in a GPU run's summary and the notes
    gpu = {"command": "python experiments/recovery_ablation/gpu_autoencoder.py", "config": "x.yaml", "batch_size": 64, "planned_steps": 10,
           "device": "GPU", "steps_reached": 10, "train_seconds": 1.0, "meshes_per_second": 640.0,
           "val_vertex_mm": {"10": 9.5}, "val_split": "val", "status": "done"}
    (tmp_path / "docs" / "figures" / "recovery_ablation_gpu.json").write_text(json.dumps({"runs": [{**gpu, "latent": 8}]}))
    (tmp_path / "docs" / "recovery_ablation_notes.md").write_text("## Why\n\nmeasured notes")
    logs.clear()
    with one_thread():
        again = run_ablation(cfgs, fake_root, tmp_path / "runs", tmp_path / "docs", log=logs.append)
    assert not [x for x in logs if "training" in x or "evaluating" in x]
    assert again["configs"]["C"]["vertex_mm"] == pytest.approx(res["configs"]["C"]["vertex_mm"])
    report = (tmp_path / "docs" / "recovery_ablation.md").read_text()
    assert "## On a GPU" in report and "9.5 mm at step 10" in report and "measured notes" in report


def test_ablation_needs_every_config(tmp_path, fake_root, capsys):
    from experiments.recovery_ablation.ablation import main

    (tmp_path / "cfg").mkdir()
    assert main([str(tmp_path / "cfg"), "--test", str(fake_root), "--out", str(tmp_path / "o")]) == 2
    assert "autoencoder.yaml: missing" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
