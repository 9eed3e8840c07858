"""blsm.spiral.shape and blsm.spiral.autodecoder: BLSM-spiral's shape space (paper 000 Eqs. 11, 17)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import blsm
from blsm import io
from blsm.model import DEFAULT_MODEL
from blsm.spiral.autodecoder import SpiralConfig, fit_codes, train_auto_decoder
from blsm.spiral.hierarchy import MeshOpsSettings, body_hierarchy, mesh_hierarchy
from blsm.spiral.shape import SpiralShapeDecoder, decoder_arrays

SMALL = MeshOpsSettings(factors=(4, 2), rings=(2, 1), lengths=(19, 7))


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny networks: intra-op threads only add contention on a busy machine (seconds per step)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _sphere(subdiv: int = 2) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdiv)
    return np.asarray(s.vertices), np.asarray(s.faces)


def _residuals(v: np.ndarray, n: int, seed: int = 0) -> torch.Tensor:
    """(n, V, 3) smooth offsets of a sphere: two latent factors (a stretch along y, a bulge in x), mm scale."""
    g = torch.Generator().manual_seed(seed)
    a, b = torch.randn(n, 1, 1, generator=g), torch.randn(n, 1, 1, generator=g)
    p = torch.as_tensor(v, dtype=torch.float32)[None]
    stretch = p * torch.tensor([0.0, 1.0, 0.0])
    bulge = p * p[..., :1].abs() * torch.tensor([1.0, 0.0, 0.0])
    return 0.01 * (a * stretch + b * bulge)


def test_decoder_shape_batch_and_bad_code():
    v, f = _sphere(2)
    ops = mesh_hierarchy(v, f, SMALL)
    dec = SpiralShapeDecoder(ops, 3, (8, 8), torch.zeros(len(v), 3), torch.full((len(v), 3), 0.01))
    z = torch.randn(5, 3)
    out = dec(z)
    assert out.shape == (5, len(v), 3)
    torch.testing.assert_close(dec(z[2:3])[0], out[2], rtol=1e-5, atol=1e-7)  # batch-independent
    assert dec.num_coeffs == 3
    with pytest.raises(ValueError, match=r"\(B, 3\)"):
        dec(torch.zeros(2, 4))


def test_auto_decoder_loss_decreases_and_codes_fit_new_bodies():
    v, f = _sphere(2)
    ops = mesh_hierarchy(v, f, SMALL)
    data = _residuals(v, 24)
    cfg = SpiralConfig(latent=2, channels=(8, 8), factors=SMALL.factors, rings=SMALL.rings,
                       lengths=SMALL.lengths, epochs=40, batch_size=8)
    dec, codes, rep = train_auto_decoder(data, ops, cfg, log_every=0)
    curve = rep["loss_curve_mm"]
    assert codes.shape == (24, 2)
    assert curve[-1] < 0.5 * curve[0], curve
    # the reported training error is the decoder at the learnt codes
    with torch.no_grad():
        err = (dec(codes) - data).norm(dim=-1).mean() * 1000
    assert abs(float(err) - rep["train_error_mm"]) < 1e-3
    # a code search (decoder fixed) on new bodies of the same family beats the zero code
    new = _residuals(v, 4, seed=1)
    z, e = fit_codes(dec, new, steps=100)
    zero = (dec(torch.zeros(4, 2)) - new).norm(dim=-1).mean(-1) * 1000
    assert float(e.mean()) < float(zero.mean())


def test_bad_options_are_value_errors():
    with pytest.raises(ValueError, match="channels"):
        SpiralConfig(channels=(8, 8))  # 4 levels by default
    with pytest.raises(ValueError, match="latent"):
        SpiralConfig(latent=0)
    from blsm.learn.training.train import ShapeConfig

    with pytest.raises(ValueError, match="shape.decoder"):
        ShapeConfig(decoder="conv")


def test_bad_option_in_a_config_file_is_an_error(tmp_path):
    from blsm.learn.training.train import load_train_config

    p = tmp_path / "c.yaml"
    p.write_text("train:\n  shape: {decoder: spiral, spiral: {latent: 4, depth: 3}}\n")
    with pytest.raises(ValueError, match="depth"):
        load_train_config(p)
    p.write_text("train:\n  shape: {decoder: spiral, spiral: {latent: 4, epochs: 2}}\n")
    assert load_train_config(p).shape.spiral.epochs == 2


@pytest.fixture(scope="module")
def spiral_model(tmp_path_factory):
    """The packaged model with a small, untrained spiral decoder in its file."""
    base = blsm.load()
    data = io.read_model(DEFAULT_MODEL)
    settings = MeshOpsSettings(factors=(8, 4), rings=(1, 1), lengths=(7, 7))
    ops = body_hierarchy(base, settings)
    torch.manual_seed(0)
    std = torch.full((base.num_vertices, 3), 0.005)
    dec = SpiralShapeDecoder(ops, 3, (4, 4), torch.zeros(base.num_vertices, 3), std)
    codes = torch.randn(data.arrays["population_bone"].shape[0], 3)
    arrays, meta = decoder_arrays(dec, ops, codes)
    data.arrays.update(arrays)
    data.meta["shape_decoder"] = meta
    path = tmp_path_factory.mktemp("spiral") / "spiral.npz"
    io.save_model(data, path)
    return path, dec, codes


def test_model_file_round_trip_gives_identical_vertices(spiral_model):
    path, dec, codes = spiral_model
    model = blsm.load(path)
    assert isinstance(model.shape_decoder, SpiralShapeDecoder)
    assert model.num_shape_coeffs == 3
    torch.testing.assert_close(model.population_shape, codes, rtol=0, atol=0)
    z = torch.randn(2, 3)
    pose = torch.randn(2, model.num_dofs) * 0.3
    out = model(pose=pose, shape=z)
    with torch.no_grad():
        want = blsm.load()(pose=pose).vertices + 0  # the same model without shape ...
    assert (out.vertices - want).abs().max() > 1e-5  # ... differs: the decoder is used
    torch.testing.assert_close(out.template[:, :, :], model.template + dec(z).detach(), rtol=0, atol=1e-7)
    again = blsm.load(path)(pose=pose, shape=z)
    assert torch.equal(again.vertices, out.vertices)
    assert model.double()(shape=z.double()).vertices.dtype == torch.float64


def test_unknown_decoder_kind_names_the_file(spiral_model, tmp_path):
    path = spiral_model[0]
    data = io.read_model(path)
    data.meta["shape_decoder"] = {**data.meta["shape_decoder"], "kind": "mlp"}
    bad = tmp_path / "bad.npz"
    io.save_model(data, bad)
    with pytest.raises(ValueError, match="bad.npz.*'mlp'"):
        blsm.load(bad)


def test_spiral_model_is_fittable(spiral_model):
    from blsm.learn.evaluation.fit import BLSMFittable, FitConfig, staged_fit

    model = blsm.load(spiral_model[0])
    fittable = BLSMFittable(model)
    assert fittable.coeff_sizes == {"bone": model.num_bone_coeffs, "shape": 3}
    g = torch.Generator().manual_seed(3)
    z = torch.randn(1, 3, generator=g)
    with torch.no_grad():
        target = model(shape=z, transl=torch.tensor([[0.1, 0.0, 0.0]])).vertices
    start = staged_fit(fittable, target, config=FitConfig(iterations=(0, 0, 0, 1)))
    res = staged_fit(fittable, target, config=FitConfig(iterations=(5, 5, 5, 10), lm_iterations=3))
    assert float(res.mean_error) < 0.5 * float(start.mean_error)
