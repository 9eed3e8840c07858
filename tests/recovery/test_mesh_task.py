"""The spiral networks end to end on the fake dataset: the autoencoder run, an image-to-mesh run
with the pretrained, frozen decoder and discriminator (Config F), its evaluation and prediction."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from recovery_helpers import CROP, one_thread, write_config

TINY_MESH = {"channels": [4, 4, 4, 4], "latent": 8, "hidden": 16}


@pytest.fixture(scope="module")
def ae_run(tmp_path_factory, mesh_cache):
    from recovery.config import load_config
    from recovery.train import train

    root = tmp_path_factory.mktemp("ae_run")
    cfg = {
        "task": "autoencoder",
        "mesh": {**TINY_MESH, "cache": str(mesh_cache)},
        "meshes": {"library": "", "stats_meshes": 64, "val_meshes": 8},
        "optim": {"lr": 1e-3, "warmup_steps": 0},
        "train": {"steps": 3, "batch_size": 2, "val_every": 3, "checkpoint_every": 3, "log_every": 1, "device": "cpu"},
    }
    with one_thread():
        assert train(load_config(write_config(root / "ae.yaml", cfg)), root / "run", log=lambda *a: None) == "done"
    return root / "run"


@pytest.fixture(scope="module")
def f_run(tmp_path_factory, ae_run, fake_root, train_cache, mesh_cache):
    from recovery import trainer
    from recovery.config import load_config
    from recovery.train import train

    root = tmp_path_factory.mktemp("mesh_run")
    cfg = {
        "task": "mesh",
        "model": {"backbone": "efficientnet_lite0", "pretrained": False},
        "data": {"train": [str(fake_root)], "val": str(fake_root), "crop": CROP, "cache": str(train_cache), "workers": 0},
        "mesh": {**TINY_MESH, "cache": str(mesh_cache), "autoencoder": str(ae_run / "last.pt"), "freeze_decoder": True},
        "began": {"enabled": True, "pretrained": True, "freeze": True},
        "loss": {"vertices": 1.0, "keypoints_2d": 1.0},
        "meshes": {"library": "", "stats_meshes": 64},
        "optim": {"lr": 1e-3, "warmup_steps": 0},
        "train": {"steps": 2, "batch_size": 2, "val_every": 2, "checkpoint_every": 2, "log_every": 1, "device": "cpu"},
    }
    mp = pytest.MonkeyPatch()
    mp.setattr(trainer, "plot_curves", lambda *a, **k: None)
    try:
        with one_thread():
            assert train(load_config(write_config(root / "mesh.yaml", cfg)), root / "run", log=lambda *a: None) == "done"
    finally:
        mp.undo()
    return root / "run"


def test_autoencoder_run_logs_vertex_error(ae_run):
    recs = [json.loads(x) for x in (ae_run / "log.jsonl").read_text().splitlines()]
    val = [r for r in recs if r["kind"] == "val"]
    assert val and val[-1]["vertex_mm"] > 0 and (ae_run / "best.pt").is_file()


def test_config_f_keeps_the_pretrained_decoder_and_discriminator(ae_run, f_run):
    from recovery.checkpoint import read_checkpoint

    ae = read_checkpoint(ae_run / "last.pt")["modules"]["ae"]
    ck = read_checkpoint(f_run / "last.pt")
    model, disc = ck["modules"]["model"], ck["modules"]["disc"]
    for k, v in ae.items():
        if k.startswith("decoder."):
            torch.testing.assert_close(model[k], v, rtol=0, atol=0)  # frozen
        torch.testing.assert_close(disc[k], v, rtol=0, atol=0)  # the discriminator is the frozen autoencoder
    torch.testing.assert_close(model["normalizer.mean"], ae["normalizer.mean"], rtol=0, atol=0)
    logs = [json.loads(x) for x in (f_run / "log.jsonl").read_text().splitlines()]
    train = [r for r in logs if r["kind"] == "train"]
    assert {"l3d", "proj", "adv", "k", "convergence", "d_real", "d_fake"} <= set(train[0])
    # k moved by Eq. 4.12 between the two steps (k_0 = 0, so it can only have risen or stayed at 0)
    assert train[1]["k"] == pytest.approx(min(max(0.0 + 1e-3 * (0.7 * train[0]["d_real"] - train[0]["d_fake"]), 0.0), 1.0))


def test_evaluate_and_predict_read_a_mesh_checkpoint(f_run, fake_root, tmp_path):
    from recovery.eval.evaluate import evaluate
    from recovery.predict import predict

    with one_thread():
        res = evaluate(f_run / "last.pt", fake_root, tmp_path / "eval", batch=4, log=lambda *a: None)
    assert res["task"] == "mesh" and res["pose_prior"] is None
    bf = res["body_frame"]
    assert bf["vertex_mm"] > 0 and bf["roughness_mm"] > 0 and bf["label_roughness_mm"] > 0
    assert (tmp_path / "eval" / "metrics.json").is_file() and (tmp_path / "eval" / "sheet.png").is_file()
    img = next(fake_root.glob("**/*.png"), None)
    if img is None:
        from PIL import Image

        img = tmp_path / "x.png"
        Image.fromarray(np.zeros((40, 30, 3), np.uint8)).save(img)
    with one_thread():
        params = predict(f_run / "last.pt", img, tmp_path / "pred")
    assert params["task"] == "mesh" and "pose" not in params and len(params["transl"]) == 3
    assert (tmp_path / "pred" / "mesh.obj").is_file() and (tmp_path / "pred" / "overlay.png").is_file()
