from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats
from scipy.special import logsumexp

from blsm.joint_limits import angles_from_unconstrained, load_dof_table
from blsm.mocap.prior import X_CLIP, PosePrior, fit_pose_prior, load_prior, uniform_sample

D = 47


@pytest.fixture(scope="module")
def table():
    return load_dof_table()


@pytest.fixture(scope="module")
def mixture():
    """A well-separated 3-component full-covariance mixture in D = 47, inside |x| < X_CLIP."""
    rng = np.random.default_rng(7)
    weights = np.array([0.5, 0.3, 0.2])
    means = rng.uniform(-1.0, 1.0, size=(3, D))
    chols = np.stack(
        [np.linalg.cholesky(a @ a.T + 0.02 * np.eye(D)) for a in 0.05 * rng.normal(size=(3, D, D))]
    )
    return weights, means, chols


def _draw(mixture, n: int, rng: np.random.Generator) -> np.ndarray:
    weights, means, chols = mixture
    comp = rng.choice(len(weights), p=weights, size=n)
    return means[comp] + np.einsum("nij,nj->ni", chols[comp], rng.normal(size=(n, D)))


def _true_log_prob(mixture, x: np.ndarray) -> np.ndarray:
    """Reference density from scipy, independent of the code under test."""
    weights, means, chols = mixture
    comps = [
        math.log(w) + stats.multivariate_normal(m, c @ c.T).logpdf(x)
        for w, m, c in zip(weights, means, chols, strict=True)
    ]
    return logsumexp(np.stack(comps, 1), axis=1)


@pytest.fixture(scope="module")
def data(mixture):
    rng = np.random.default_rng(0)
    return _draw(mixture, 6000, rng), _draw(mixture, 2000, rng)


@pytest.fixture(scope="module")
def fitted(data, table):
    return fit_pose_prior(
        data[0], table.limits_tensor(), table.names, k=3, seed=0, meta={"clips": ["synthetic"]}
    )


def test_fit_recovers_a_known_mixture_and_beats_one_gaussian(mixture, data, fitted, table):
    train, held_out = data
    true_ll = _true_log_prob(mixture, held_out).mean()
    fit_ll = fitted.log_prob(torch.from_numpy(held_out)).mean().item()
    single = fit_pose_prior(train, table.limits_tensor(), table.names, k=1)
    single_ll = single.log_prob(torch.from_numpy(held_out)).mean().item()
    # 3 x 1175 parameters from 6000 frames cost about 0.3 nats per held-out frame.
    assert true_ll - 0.6 < fit_ll < true_ll + 0.1
    assert single_ll < true_ll - 5.0
    assert np.sort(fitted.weights.numpy()) == pytest.approx(np.sort(mixture[0]), abs=0.03)
    fit = fitted.meta["fit"]
    assert fit["converged"] and fit["k"] == 3 and fit["n_frames"] == 6000
    assert fitted.meta["clips"] == ["synthetic"]
    assert fitted.dof_names == table.names


def test_em_separates_components_that_k_means_cannot(table):
    # Same mean, different spread: k-means splits by distance, only EM iterations recover 50/50.
    rng = np.random.default_rng(3)
    narrow = rng.integers(2, size=3000) == 0
    x = np.where(narrow[:, None], 0.3, 0.8) * rng.normal(size=(3000, D))
    one_step = fit_pose_prior(x, table.limits_tensor(), table.names, k=2, iters=1)
    prior = fit_pose_prior(x, table.limits_tensor(), table.names, k=2)
    assert prior.meta["fit"]["converged"] and not one_step.meta["fit"]["converged"]
    assert prior.meta["fit"]["mean_log_likelihood"] > one_step.meta["fit"]["mean_log_likelihood"] + 1.0
    assert prior.weights.numpy() == pytest.approx([0.5, 0.5], abs=0.03)
    cov = prior.scale_tril @ prior.scale_tril.mT  # (K, D, D)
    spread = np.sort(cov.diagonal(dim1=1, dim2=2).mean(1).sqrt().numpy())
    assert spread == pytest.approx([0.3, 0.8], abs=0.02)


def test_log_prob_matches_torch_distributions_in_float64_and_float32(fitted):
    x = fitted.sample(64, torch.Generator().manual_seed(1))
    mvn = torch.distributions.MultivariateNormal(
        fitted.means, scale_tril=fitted.scale_tril, validate_args=False
    )
    ref = torch.distributions.MixtureSameFamily(torch.distributions.Categorical(fitted.weights), mvn)
    torch.testing.assert_close(fitted.log_prob(x), ref.log_prob(x), rtol=1e-10, atol=1e-8)
    lp32 = fitted(x.float())
    assert lp32.dtype == torch.float32
    torch.testing.assert_close(lp32, ref.log_prob(x).float(), rtol=1e-4, atol=1e-2)
    x.requires_grad_(True)
    (grad,) = torch.autograd.grad(fitted.log_prob(x).sum(), x)
    (ref_grad,) = torch.autograd.grad(ref.log_prob(x).sum(), x)
    torch.testing.assert_close(grad, ref_grad)


def test_samples_map_inside_the_limits_and_are_reproducible(fitted, table):
    limits = table.limits_tensor()
    a = fitted.sample(5000, torch.Generator().manual_seed(3))
    b = fitted.sample(5000, torch.Generator().manual_seed(3))
    c = fitted.sample(5000, torch.Generator().manual_seed(4))
    assert a.shape == (5000, D) and torch.equal(a, b) and not torch.equal(a, c)
    theta = fitted.angles(a)
    torch.testing.assert_close(theta, angles_from_unconstrained(a, limits))
    assert (theta >= limits[:, 0]).all() and (theta <= limits[:, 1]).all()
    assert fitted.sample(0).shape == (0, D)


def test_sample_moments_match_the_mixture(mixture, table):
    weights, means, chols = mixture
    prior = PosePrior(weights, means, chols, table.limits_tensor(), table.names)
    x = prior.sample(40000, torch.Generator().manual_seed(0)).numpy()
    mean = weights @ means
    cov = sum(
        w * (c @ c.T + np.outer(m, m)) for w, m, c in zip(weights, means, chols, strict=True)
    ) - np.outer(mean, mean)
    assert np.abs(x.mean(0) - mean).max() < 0.03
    assert np.abs(np.cov(x, rowvar=False) - cov).max() < 0.04
    # Per component: the scale must be L (not L^T) for the covariance to come out right.
    within = x - means[np.argmin(((x[:, None] - means) ** 2).sum(-1), 1)]
    pooled = sum(w * c @ c.T for w, c in zip(weights, chols, strict=True))
    assert np.abs(within.T @ within / len(x) - pooled).max() < 0.01


def test_uniform_sample_gives_uniform_angles_inside_the_limits(table):
    limits = table.limits_tensor()
    x = uniform_sample(20000, limits, torch.Generator().manual_seed(0))
    assert x.shape == (20000, D) and torch.isfinite(x).all()
    assert torch.equal(x, uniform_sample(20000, limits, torch.Generator().manual_seed(0)))
    theta = angles_from_unconstrained(x, limits).numpy()
    lo, hi = limits[:, 0].numpy(), limits[:, 1].numpy()
    assert (theta >= lo).all() and (theta <= hi).all()
    u = (theta - lo) / (hi - lo)  # (N, D), uniform on [0, 1] per DoF
    assert np.abs(u.mean(0) - 0.5).max() < 4.5 / math.sqrt(12 * 20000)
    p_values = [stats.kstest(u[:, i], "uniform").pvalue for i in range(D)]
    assert min(p_values) > 1e-4


def test_log_prob_prefers_the_data_to_uniform_poses(fitted, data, table):
    near = fitted.log_prob(torch.from_numpy(data[1])).numpy()
    far = fitted.log_prob(
        uniform_sample(2000, table.limits_tensor(), torch.Generator().manual_seed(0))
    ).numpy()
    assert np.quantile(near, 0.01) > np.quantile(far, 0.99)


def test_fit_clips_saturated_values_and_restarts_empty_components(table):
    rng = np.random.default_rng(1)
    # Two distinct poses repeated: k-means leaves components empty and EM has to restart them.
    x = np.repeat(rng.uniform(-1, 1, size=(2, D)), 100, axis=0)
    x[:100, 0] = np.inf  # atanh of an angle exactly on its limit
    x[100:, 1] = -50.0
    prior = fit_pose_prior(x, table.limits_tensor(), table.names, k=4, seed=0, iters=20)
    w = prior.weights.numpy()
    assert (w > 0).all() and w.sum() == pytest.approx(1.0)
    assert prior.meta["fit"]["restarts"] >= 1
    assert prior.meta["fit"]["clipped_fraction"] == pytest.approx(200 / x.size)
    assert prior.means.abs().max().item() == pytest.approx(X_CLIP)
    assert torch.isfinite(prior.log_prob(torch.from_numpy(x.clip(-X_CLIP, X_CLIP)))).all()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda x: x[:, :-1], "x must be"),
        (lambda x: x[:20], "needs at least 30"),
        (lambda x: np.where(np.arange(len(x))[:, None] == 5, np.nan, x), "NaN"),
    ],
)
def test_fit_rejects_bad_input(data, table, change, message):
    with pytest.raises(ValueError, match=message):
        fit_pose_prior(change(data[0][:100]), table.limits_tensor(), table.names, k=3)


def test_save_load_round_trip(fitted, data, tmp_path):
    path = fitted.save(tmp_path / "sub" / "prior.npz")
    assert sorted(p.name for p in path.parent.iterdir()) == ["prior.npz"]  # no temporary left behind
    loaded = load_prior(path)
    x = torch.from_numpy(data[1])
    assert torch.equal(loaded.log_prob(x), fitted.log_prob(x))
    assert loaded.dof_names == fitted.dof_names and loaded.meta == fitted.meta
    assert torch.equal(PosePrior.load(path).limits, fitted.limits)


def _corrupt(raw: dict, key: str, value) -> dict:
    return {**raw, key: value}


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda r: _corrupt(r, "format", np.array("blsm-model")), "not a BLSM pose prior file"),
        (lambda r: _corrupt(r, "format_version", np.array(2)), "format_version 2"),
        (lambda r: _corrupt(r, "weights", r["weights"] * 1.1), "sum to 1"),
        (lambda r: _corrupt(r, "weights", r["weights"] * np.array([-1.0, 1.0, 1.0])), "positive"),
        (lambda r: _corrupt(r, "means", np.where(np.eye(3, D) > 0, np.nan, r["means"])), "non-finite"),
        (lambda r: _corrupt(r, "means", r["means"][:, :-1]), "shape"),
        (lambda r: _corrupt(r, "limits", r["limits"][:, :1]), "shape"),
        (lambda r: _corrupt(r, "scale_tril", r["scale_tril"].transpose(0, 2, 1)), "lower-triangular"),
        (lambda r: _corrupt(r, "scale_tril", -r["scale_tril"]), "positive diagonal"),
        (lambda r: _corrupt(r, "limits", r["limits"] + 10.0), "limits of"),
        (lambda r: {k: v for k, v in r.items() if k != "scale_tril"}, "missing array 'scale_tril'"),
        (lambda r: _corrupt(r, "dof_names_json", np.array("{")), "dof_names_json"),
    ],
)
def test_corrupt_files_raise_naming_the_file(fitted, tmp_path, edit, message):
    good = fitted.save(tmp_path / "good.npz")
    with np.load(good) as npz:
        raw = {k: npz[k] for k in npz.files}
    bad = tmp_path / "bad.npz"
    np.savez(bad, **edit(raw))
    with pytest.raises(ValueError, match=message) as info:
        load_prior(bad)
    assert str(info.value).startswith(f"{bad}: ")
    assert "\n" not in str(info.value)


def test_missing_and_unreadable_files_raise_naming_the_file(tmp_path):
    missing = tmp_path / "missing.npz"
    with pytest.raises(ValueError, match="no such pose prior file") as info:
        load_prior(missing)
    assert str(info.value).startswith(f"{missing}: ")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a readable") as info:
        PosePrior.load(junk)
    assert str(info.value).startswith(f"{junk}: ")


def test_save_refuses_an_invalid_prior(fitted, tmp_path):
    prior = PosePrior(fitted.weights, fitted.means, fitted.scale_tril, fitted.limits, fitted.dof_names)
    prior.weights.mul_(2.0)
    path = tmp_path / "p.npz"
    with pytest.raises(ValueError, match="sum to 1") as info:
        prior.save(path)
    assert str(info.value).startswith(f"{path}: ")
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    "pose",
    [torch.zeros(D), torch.zeros(2, D - 1), torch.zeros(2, D, 1), torch.zeros(2, D, dtype=torch.long)],
)
def test_log_prob_rejects_wrong_shapes(fitted, pose):
    with pytest.raises(ValueError, match="pose must be"):
        fitted.log_prob(pose)
