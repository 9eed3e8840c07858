"""Tests for blsm/learn/training/train.py: learning the model from registrations (Eqs. 5.26-5.31).

Training data come from the packaged model itself (random bone and shape coefficients, the rest pose
and poses from the packaged CMU prior, 0.5 mm noise); the initial model is the packaged one with
its blend weights blurred towards the parent bones, so step 5 has something to recover.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import blsm
from blsm import io
from blsm.learn.training import train as T
from blsm.learn.training.bases import bone_mirror_index
from blsm.mocap.prior import load_prior
from blsm.model import BLSM, DEFAULT_MODEL

PRIOR = Path(blsm.__file__).parent / "data" / "pose_prior_cmu.npz"


def make_registrations(model, n_subjects, n_posed, gen, noise=5e-4, split="train", first=0, bone_dims=None):
    """Rest-pose plus ``n_posed`` posed registrations per random subject of ``model``."""
    prior = load_prior(PRIOR)
    cb = torch.randn(n_subjects, model.num_bone_coeffs, generator=gen)
    if bone_dims is not None:
        cb[:, bone_dims:] = 0.0
    cs = torch.randn(n_subjects, model.num_shape_coeffs, generator=gen)
    regs = []
    for s in range(n_subjects):
        n = 1 + n_posed
        ang = prior.angles(prior.sample(n, generator=gen)).float()
        ang[0] = 0.0
        go = 0.1 * torch.randn(n, 3, generator=gen)
        tr = 0.1 * torch.randn(n, 3, generator=gen)
        with torch.no_grad():
            out = model(angles=ang, bone=cb[s : s + 1].expand(n, -1), shape=cs[s : s + 1].expand(n, -1), global_orient=go, transl=tr)
        verts = out.vertices + noise * torch.randn(out.vertices.shape, generator=gen)
        stage1 = out.bone_scales * (1.0 + 0.01 * torch.randn(n, model.num_joints, generator=gen))
        for k in range(n):
            meta = {"subject": f"s{first + s}", "rest": k == 0, "split": split}
            regs.append(T.TrainingRegistration(verts[k].numpy(), stage1[k].numpy(), ang[k].numpy(), go[k].numpy(), tr[k].numpy(), meta))
    return regs


def blurred_model() -> BLSM:
    """The packaged model with 25 % of every bone's weight moved to its parent (still symmetric)."""
    data = io.read_model(DEFAULT_MODEL)
    w = data.arrays["weights"].astype(np.float64)
    parents = data.meta["parents"]
    moved = np.zeros_like(w)
    for j, p in enumerate(parents):
        moved[:, max(p, 0)] += w[:, j]
    w = 0.75 * w + 0.25 * moved
    data.arrays["weights"] = (w / w.sum(1, keepdims=True)).astype(np.float32)
    return BLSM(data)


def small_config() -> T.TrainConfig:
    cfg = T.TrainConfig()
    cfg.bone.num_coeffs = 10
    cfg.fit.iterations = 100
    cfg.fit.num_vertices = 1500
    cfg.correctives.alternations = 1
    cfg.shape.num_coeffs = 12
    cfg.weights.rounds = 2
    cfg.weights.iterations = 100
    cfg.weights.batch_size = 8
    return cfg


@pytest.fixture(scope="module")
def learned(model):
    torch.set_num_threads(1)
    gen = torch.Generator().manual_seed(1)
    regs = make_registrations(model, 16, 2, gen) + make_registrations(model, 3, 1, gen, split="test", first=100)
    initial = blurred_model()
    data, report = T.learn_model(initial, regs, small_config())
    return initial, data, report


def test_learned_model_reproduces_heldout_bodies(learned):
    _, _, report = learned
    err = report["errors_mm"]
    assert err["test"] < 4.0, err  # noise alone is ~0.8 mm mean distance
    assert err["correctives_0"] < 0.6 * err["fit_0"], err  # Eq. 5.27 helps
    assert err["shape"] < 0.5 * err["correctives_0"], err  # Eq. 5.8 helps
    assert report["bone_pca_explained_first3"] > 0.5
    assert set(report["seconds"]) >= {"bone_basis", "fit_0", "correctives_0", "shape_basis", "weights", "test", "total"}


def test_weights_learning_reduces_posed_error(learned):
    initial, data, report = learned
    err = report["errors_mm"]
    assert err["posed_after_weights"] < 0.7 * err["posed_before_weights"], err
    true_w = blsm.load().weights.numpy()
    w = data.arrays["weights"]
    # The learned weights moved towards the weights that made the data.
    assert np.abs(w - true_w).mean() < 0.9 * np.abs(initial.weights.numpy() - true_w).mean()


def test_weights_normalised_nonnegative_symmetric(learned, model):
    _, data, _ = learned
    w = data.arrays["weights"]
    assert (w >= 0).all()
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-5)
    mirror = data.arrays["vertex_mirror"]
    bm = bone_mirror_index(model.bone_names)
    np.testing.assert_allclose(w[mirror][:, bm], w, atol=1e-6)


def test_bases_symmetric(learned, model):
    _, data, _ = learned
    mirror = data.arrays["vertex_mirror"]
    flip = np.array([-1.0, 1.0, 1.0], dtype=np.float32)
    for key in ("bone_correctives", "shape_basis"):
        b = data.arrays[key]
        np.testing.assert_allclose(b[:, mirror] * flip, b, atol=1e-6, err_msg=key)
    t = data.arrays["template"]
    np.testing.assert_allclose(t[mirror] * flip, t, atol=1e-6)
    bb = data.arrays["bone_basis"]
    np.testing.assert_allclose(bb[:, bone_mirror_index(model.bone_names)], bb, atol=1e-6)


def test_saved_model_loads_and_runs(learned, tmp_path):
    _, data, _ = learned
    path = io.save_model(data, tmp_path / "learned.npz")
    m = blsm.load(path)
    assert m.num_bone_coeffs == 10 and m.num_shape_coeffs == 12 and m.num_vertices == 7002
    np.testing.assert_allclose(m.bone_mean.numpy(), 1.0, atol=1e-5)  # rebased skeleton
    out = m(bone=torch.randn(2, 10), shape=torch.randn(2, 12), pose=torch.randn(2, 47))
    assert out.vertices.shape == (2, 7002, 3) and torch.isfinite(out.vertices).all()
    assert m.population_bone.shape == (16, 10) and m.population_shape.shape == (16, 12)


def test_config_files_load():
    root = Path(__file__).resolve().parents[2] / "configs" / "blsm"
    small = T.load_train_config(root / "train_small.yaml")
    default = T.load_train_config(root / "train_default.yaml")
    assert small.fit.iterations < default.fit.iterations
    assert default.shape.num_coeffs == 64


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("train:\n  fit:\n    iters: 3\n", "train.fit.iters: unknown key"),
        ("train:\n  fit:\n    iterations: many\n", "train.fit.iterations: expected an integer"),
        ("train:\n  weights:\n    enabled: 1\n", "train.weights.enabled: expected true or false"),
        ("train:\n  shape:\n    symmetry: left\n", "train.shape: shape.symmetry must be one of"),
        ("trian: {}\n", "trian: unknown key"),
        ("train: [1, 2]\n", "train: expected a mapping"),
    ],
)
def test_bad_config_is_one_line_error(tmp_path, text, message):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ValueError) as exc:
        T.load_train_config(path)
    msg = str(exc.value)
    assert msg.startswith(f"{path}: ") and message in msg and "\n" not in msg


def test_bad_registrations(model):
    gen = torch.Generator().manual_seed(0)
    regs = make_registrations(model, 3, 0, gen)
    with pytest.raises(ValueError, match="rest-pose training registrations"):
        T.learn_model(model, regs, small_config())
    regs[1].angles = np.zeros(12, dtype=np.float32)
    with pytest.raises(ValueError, match=r"registration 1: angles must be \(47,\)"):
        T.learn_model(model, regs, small_config())
    regs[1].angles = np.full(47, np.nan, dtype=np.float32)
    with pytest.raises(ValueError, match="registration 1: angles has non-finite values"):
        T.learn_model(model, regs, small_config())


def test_is_rest_pose():
    assert T.is_rest_pose({"rest": True}) and not T.is_rest_pose({"rest": False, "pose_id": "rest"})
    assert T.is_rest_pose({"pose_id": "rest"}) and T.is_rest_pose({"pose_id": 0})
    assert not T.is_rest_pose({"pose_id": "walk_3"}) and T.is_rest_pose({"scan_index": 0})
