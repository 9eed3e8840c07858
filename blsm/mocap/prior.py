"""A pose prior over the 47 BLSM atoms: a Gaussian mixture in the unconstrained space of Eq. 6.

The model's pose vector is unconstrained: an atom's angle is ``theta = half * tanh(x) + mid``
(paper 000 Eq. 6, :func:`blsm.joint_limits.angles_from_unconstrained`). The prior is a
full-covariance Gaussian mixture over those unconstrained values ``x`` (D = 47), not over the angles,
for two reasons: a sample of the mixture maps through Eq. 6 to angles that are inside the joint
limits by construction, and ``log_prob`` is a smooth penalty on exactly the variable a fitter
optimises.

Mocap angles that sit on a limit have ``x = atanh(+-1) = +-inf``, so training values are clipped to
``|x| <= X_CLIP`` (3.0: ``tanh(3) = 0.995``, i.e. within 0.25 % of the range from a limit) before
fitting; without that a few saturated frames would blow up the covariances.

The prior file is one versioned ``.npz`` archive (format ``blsm-pose-prior``, version 1), written
atomically (temporary file in the same folder, then rename):

==================  ==============  ================================================================
key                 shape / dtype   meaning
==================  ==============  ================================================================
format              str             ``"blsm-pose-prior"``
format_version      int             1
dof_names_json      str             JSON list of the D atom names, in pose-vector order
meta_json           str             JSON object: provenance (source clips, fps, frames, fit settings)
weights             (K,) float64    mixture weights, > 0, sum to 1
means               (K, D) float64  component means of ``x``
scale_tril          (K, D, D)       lower Cholesky factors of the component covariances (float64)
limits              (D, 2) float64  ``[theta_min, theta_max]`` in radians that Eq. 6 maps into
==================  ==============  ================================================================
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg
import torch
from torch import nn

from blsm.io import read_versioned_npz, write_versioned_npz
from blsm.joint_limits import angles_from_unconstrained, unconstrained_from_angles

FORMAT = "blsm-pose-prior"
FORMAT_VERSION = 1
DEFAULT_PRIOR = Path(__file__).resolve().parents[1] / "data" / "pose_prior_cmu.npz"
"""The packaged CMU pose prior (``make prior``; clips 007_12 and 005_20 held out)."""
X_CLIP = 3.0  # |x| bound applied to training values; tanh(3) = 0.995
WEIGHT_SUM_TOL = 1e-5

_ARRAYS = ("weights", "means", "scale_tril", "limits")
_LOG_2PI = math.log(2.0 * math.pi)
_LLOYD_STEPS = 10  # k-means refinement of the k-means++ seeds before EM
_TINY = 1e-300  # responsibilities below this are set to 0
_CHUNK = 512  # frames per block in EM, keeping the (C, K, D) temporaries in cache


def _validate(arrays: dict[str, np.ndarray], dof_names: Sequence[str], where: str) -> None:
    """Check presence, shapes, finiteness and the mixture's constraints; raise ValueError naming ``where``."""
    for key in _ARRAYS:
        if key not in arrays:
            raise ValueError(f"{where}: missing array {key!r}")
        if arrays[key].dtype.kind != "f":
            raise ValueError(f"{where}: array {key!r} has dtype {arrays[key].dtype}, expected floating point")
    w, mu, tril, lim = (arrays[key] for key in _ARRAYS)
    if w.ndim != 1 or w.shape[0] < 1:
        raise ValueError(f"{where}: weights must be (K,) with K >= 1, got shape {w.shape}")
    k = w.shape[0]
    if mu.ndim != 2 or mu.shape[0] != k or mu.shape[1] < 1:
        raise ValueError(f"{where}: means must be (K, D) with K = {k}, got shape {mu.shape}")
    d = mu.shape[1]
    if tril.shape != (k, d, d):
        raise ValueError(f"{where}: scale_tril must be (K, D, D) = {(k, d, d)}, got shape {tril.shape}")
    if lim.shape != (d, 2):
        raise ValueError(f"{where}: limits must be (D, 2) = {(d, 2)}, got shape {lim.shape}")
    if len(dof_names) != d or not all(isinstance(name, str) for name in dof_names):
        raise ValueError(f"{where}: dof_names must be {d} strings, got {len(dof_names)} entries")
    for key in _ARRAYS:
        if not np.isfinite(arrays[key]).all():
            raise ValueError(f"{where}: array {key!r} has non-finite values")
    if (w <= 0).any() or abs(float(w.sum()) - 1.0) > WEIGHT_SUM_TOL:
        raise ValueError(f"{where}: weights must be positive and sum to 1, got sum {float(w.sum()):.8g}")
    if np.triu(tril, 1).any():
        raise ValueError(f"{where}: scale_tril must be lower-triangular")
    if (np.diagonal(tril, axis1=1, axis2=2) <= 0).any():
        raise ValueError(f"{where}: scale_tril must have a positive diagonal")
    bad = np.flatnonzero(~((lim[:, 0] <= 0.0) & (lim[:, 1] >= 0.0) & (lim[:, 0] < lim[:, 1])))
    if bad.size:
        raise ValueError(
            f"{where}: limits of {dof_names[bad[0]]!r} are {lim[bad[0]].tolist()}; "
            "need theta_min <= 0 <= theta_max and theta_min < theta_max"
        )


def _as_float64(a: torch.Tensor | np.ndarray) -> np.ndarray:
    if isinstance(a, torch.Tensor):
        a = a.detach().cpu().numpy()
    return np.array(a, dtype=np.float64)  # a copy: buffers never alias the caller's arrays


class PosePrior(nn.Module):
    """Gaussian mixture density over unconstrained pose values ``x`` (Eq. 6), with K components.

    Buffers (follow ``.to(device)`` / ``.double()``): ``weights`` (K,), ``means`` (K, D),
    ``scale_tril`` (K, D, D) lower Cholesky factors of the covariances, ``limits`` (D, 2) radians.
    Calling the module is :meth:`log_prob`.

    Args:
        weights: (K,) mixture weights, positive, summing to 1.
        means: (K, D) component means.
        scale_tril: (K, D, D) lower-triangular Cholesky factors with a positive diagonal.
        limits: (D, 2) ``[theta_min, theta_max]`` in radians, ``theta_min <= 0 <= theta_max``.
        dof_names: the D atom names in pose-vector order.
        meta: JSON-serialisable provenance (source clips, fps, frame count, fit settings).

    Raises:
        ValueError: if the parameters are inconsistent or ``meta`` is not JSON-serialisable.
    """

    weights: torch.Tensor
    means: torch.Tensor
    scale_tril: torch.Tensor
    limits: torch.Tensor

    def __init__(
        self,
        weights: torch.Tensor | np.ndarray,
        means: torch.Tensor | np.ndarray,
        scale_tril: torch.Tensor | np.ndarray,
        limits: torch.Tensor | np.ndarray,
        dof_names: Sequence[str],
        meta: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        arrays = {
            key: _as_float64(value)
            for key, value in zip(_ARRAYS, (weights, means, scale_tril, limits), strict=True)
        }
        dof_names = list(dof_names)
        _validate(arrays, dof_names, "PosePrior")
        meta = dict(meta or {})
        try:
            json.dumps(meta)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"PosePrior: meta must be JSON-serialisable ({exc})") from exc
        for key, value in arrays.items():
            # Rebuilt from the prior file, so not part of a parent module's state_dict.
            self.register_buffer(key, torch.from_numpy(value), persistent=False)
        self.dof_names: list[str] = dof_names
        self.meta: dict[str, Any] = meta

    @property
    def num_components(self) -> int:
        """K, the number of mixture components."""
        return self.weights.shape[0]

    @property
    def dim(self) -> int:
        """D, the number of pose atoms."""
        return self.means.shape[1]

    def extra_repr(self) -> str:
        return f"num_components={self.num_components}, dim={self.dim}"

    def _check_pose(self, pose: torch.Tensor) -> None:
        if not isinstance(pose, torch.Tensor) or not pose.is_floating_point():
            raise ValueError("pose must be a floating-point torch.Tensor")
        if pose.ndim != 2 or pose.shape[1] != self.dim:
            raise ValueError(f"pose must be (B, {self.dim}), got {tuple(pose.shape)}")

    def log_prob(self, pose: torch.Tensor) -> torch.Tensor:
        """Log density of unconstrained pose values under the mixture (differentiable in ``pose``).

        Args:
            pose: (B, D) unconstrained values ``x`` of Eq. 6, float32 or float64.

        Returns:
            (B,) log densities in the dtype of ``pose``.

        Raises:
            ValueError: if ``pose`` is not a floating-point (B, D) tensor.
        """
        self._check_pose(pose)
        dtype = pose.dtype
        log_w = torch.log(self.weights.to(dtype))  # (K,)
        means = self.means.to(dtype)
        tril = self.scale_tril.to(dtype)
        diff = (pose.unsqueeze(0) - means.unsqueeze(1)).transpose(1, 2)  # (K, D, B)
        z = torch.linalg.solve_triangular(tril, diff, upper=False)  # (K, D, B)
        maha = z.square().sum(1)  # (K, B)
        half_logdet = torch.log(torch.diagonal(tril, dim1=-2, dim2=-1)).sum(-1)  # (K,)
        log_comp = (log_w - half_logdet - 0.5 * self.dim * _LOG_2PI).unsqueeze(1) - 0.5 * maha
        return torch.logsumexp(log_comp, dim=0)  # (B,)

    def forward(self, pose: torch.Tensor) -> torch.Tensor:
        """Same as :meth:`log_prob`."""
        return self.log_prob(pose)

    def sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """Draw unconstrained pose values; reproducible for a seeded ``generator``.

        Args:
            n: number of samples, >= 0.
            generator: random generator on the buffers' device (default: torch's global one).

        Returns:
            (n, D) unconstrained values in the buffers' dtype; map them to angles with :meth:`angles`.
        """
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise ValueError(f"n must be a non-negative int, got {n!r}")
        if n == 0:
            return self.means.new_empty((0, self.dim))
        comp = torch.multinomial(self.weights, n, replacement=True, generator=generator)  # (n,)
        eps = torch.randn(n, self.dim, generator=generator, dtype=self.means.dtype, device=self.means.device)
        out = torch.empty_like(eps)  # (n, D)
        # One product per component rather than gathering an (n, D, D) stack of factors.
        for j in range(self.num_components):
            idx = (comp == j).nonzero().squeeze(1)
            out[idx] = self.means[j] + eps[idx] @ self.scale_tril[j].T
        return out

    def angles(self, pose: torch.Tensor) -> torch.Tensor:
        """Eq. 6: joint angles in radians, (B, D), of unconstrained values ``pose`` (B, D)."""
        self._check_pose(pose)
        return angles_from_unconstrained(pose, self.limits.to(pose.dtype))

    def save(self, path: str | Path) -> Path:
        """Write the prior to a ``.npz`` file atomically (temporary file, then rename).

        Args:
            path: destination file; its folder is created if needed.

        Returns:
            The path written.

        Raises:
            ValueError: naming the file, if the buffers no longer form a valid mixture.
        """
        path = Path(path)
        arrays = {key: _as_float64(getattr(self, key)) for key in _ARRAYS}
        _validate(arrays, self.dof_names, str(path))
        entries = {
            "dof_names_json": np.array(json.dumps(self.dof_names)),
            "meta_json": np.array(json.dumps(self.meta, sort_keys=True)),
            **arrays,
        }
        return write_versioned_npz(path, FORMAT, FORMAT_VERSION, entries)

    @classmethod
    def load(cls, path: str | Path) -> PosePrior:
        """Read and validate a prior file written by :meth:`save`.

        Args:
            path: a ``blsm-pose-prior`` ``.npz`` file.

        Returns:
            The prior, with float64 buffers on the CPU.

        Raises:
            ValueError: ``"<path>: <problem>"`` for a missing, unreadable, foreign, wrongly versioned
                or inconsistent file.
        """
        path = Path(path)
        raw = read_versioned_npz(path, FORMAT, FORMAT_VERSION, "pose prior")
        try:
            dof_names = json.loads(str(raw["dof_names_json"]))
            meta = json.loads(str(raw["meta_json"]))
        except (KeyError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: bad or missing dof_names_json/meta_json ({exc})") from exc
        if not isinstance(dof_names, list):
            raise ValueError(f"{path}: dof_names_json must hold a JSON list")
        if not isinstance(meta, dict):
            raise ValueError(f"{path}: meta_json must hold a JSON object")
        arrays = {key: raw[key] for key in _ARRAYS if key in raw}
        _validate(arrays, dof_names, str(path))
        return cls(**{key: arrays[key] for key in _ARRAYS}, dof_names=dof_names, meta=meta)


def load_prior(path: str | Path) -> PosePrior:
    """Read and validate a pose prior file; see :meth:`PosePrior.load`."""
    return PosePrior.load(path)


def uniform_sample(
    n: int, limits: torch.Tensor | np.ndarray, generator: torch.Generator | None = None
) -> torch.Tensor:
    """Unconstrained values whose angles are uniform within the limits (stress data, not a prior).

    Args:
        n: number of samples, >= 0.
        limits: (D, 2) ``[theta_min, theta_max]`` in radians.
        generator: random generator on the CPU / ``limits``' device (default: torch's global one).

    Returns:
        (n, D) unconstrained values ``x`` (inverse of Eq. 6 of uniform angles), in ``limits``' dtype.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise ValueError(f"n must be a non-negative int, got {n!r}")
    limits = torch.as_tensor(limits)
    if limits.ndim != 2 or limits.shape[1] != 2 or not limits.is_floating_point():
        raise ValueError(f"limits must be a floating-point (D, 2) array, got {tuple(limits.shape)}")
    u = torch.rand(n, limits.shape[0], generator=generator, dtype=limits.dtype, device=limits.device)
    theta = limits[:, 0] + u * (limits[:, 1] - limits[:, 0])  # (n, D)
    return unconstrained_from_angles(theta, limits)


# --- EM fit (float64 numpy) -----------------------------------------------------------------------


def _kmeans_init(x: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeds refined by a few Lloyd steps; returns (N,) hard labels in [0, k)."""
    n = x.shape[0]
    centers = np.empty((k, x.shape[1]))
    centers[0] = x[rng.integers(n)]
    d2 = np.square(x - centers[0]).sum(1)  # (N,)
    for j in range(1, k):
        total = d2.sum()
        idx = rng.choice(n, p=d2 / total) if total > 0 else rng.integers(n)
        centers[j] = x[idx]
        d2 = np.minimum(d2, np.square(x - centers[j]).sum(1))
    sq = np.square(x).sum(1)  # (N,)
    labels = np.full(n, -1)
    for _ in range(_LLOYD_STEPS):
        new = (sq[:, None] - 2.0 * x @ centers.T + np.square(centers).sum(1)).argmin(1)  # (N,)
        if np.array_equal(new, labels):
            break
        labels = new
        counts = np.bincount(labels, minlength=k)  # (K,)
        sums = np.eye(k)[labels].T @ x  # (K, D)
        filled = counts > 0  # an emptied cluster keeps its seed; EM restarts it if need be
        centers[filled] = sums[filled] / counts[filled, None]
    return labels


def _e_step(
    x1: np.ndarray, weights: np.ndarray, means: np.ndarray, chols: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Responsibilities (N, K) and per-frame log-likelihoods (N,), via a stable log-sum-exp.

    ``x1`` is the (N, D + 1) data with a trailing column of ones, which folds the mean into the
    whitening product: ``[x, 1] @ [[L^-T], [-mu L^-T]] = (x - mu) L^-T``.
    """
    n, d = x1.shape[0], x1.shape[1] - 1
    k = weights.shape[0]
    eye = np.eye(d)
    prec_t = np.stack([scipy.linalg.solve_triangular(c, eye, lower=True).T for c in chols])  # (K, D, D)
    shift = np.einsum("kd,kde->ke", means, prec_t)  # (K, D)
    # All components in one (C, D + 1) @ (D + 1, K * D) product per block of frames.
    whiten = np.vstack([prec_t.transpose(1, 0, 2).reshape(d, k * d), -shift.reshape(1, k * d)])
    const = np.log(weights) - np.log(np.diagonal(chols, axis1=1, axis2=2)).sum(1) - 0.5 * d * _LOG_2PI
    log_comp = np.empty((n, k))
    for s in range(0, n, _CHUNK):
        y = (x1[s : s + _CHUNK] @ whiten).reshape(-1, k, d)  # (C, K, D)
        log_comp[s : s + _CHUNK] = const - 0.5 * np.einsum("ckd,ckd->ck", y, y)
    top = log_comp.max(1, keepdims=True)  # (N, 1)
    ll = top[:, 0] + np.log(np.exp(log_comp - top).sum(1))  # (N,)
    resp = np.exp(log_comp - ll[:, None])  # (N, K)
    resp[resp < _TINY] = 0.0  # flush denormals, which slow every later product by orders of magnitude
    return resp, ll


def _m_step(
    x: np.ndarray, resp: np.ndarray, reg: float, rng: np.random.Generator, global_cov: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Weights (K,), means (K, D) and Cholesky factors (K, D, D); empty components restarted."""
    n, d = x.shape
    k = resp.shape[1]
    nk = resp.sum(0)  # (K,)
    empty = nk < 1.0  # less than one frame's worth of responsibility
    safe_nk = np.maximum(nk, 1.0)[:, None]  # empty components are overwritten below
    means = resp.T @ x / safe_nk  # (K, D)
    # Uncentred second moments, all components in one product per block; with |x| <= X_CLIP the
    # cancellation in E[x x^T] - mu mu^T is far below reg.
    second = np.zeros((d, k * d))
    for s in range(0, n, _CHUNK):
        xs = x[s : s + _CHUNK]  # (C, D)
        second += xs.T @ (resp[s : s + _CHUNK, :, None] * xs[:, None, :]).reshape(len(xs), k * d)
    covs = second.reshape(d, k, d).transpose(1, 0, 2) / safe_nk[:, :, None]  # (K, D, D)
    covs -= np.einsum("ki,kj->kij", means, means)
    covs = 0.5 * (covs + covs.transpose(0, 2, 1)) + reg * np.eye(d)
    for j in np.flatnonzero(empty):
        # Restart at a random frame with the data's spread rather than dropping it, so k is kept.
        means[j] = x[rng.integers(n)]
        covs[j] = global_cov + reg * np.eye(d)
    weights = np.where(empty, 1.0 / k, nk / n)
    return weights / weights.sum(), means, np.linalg.cholesky(covs), int(empty.sum())


def fit_pose_prior(
    x: np.ndarray,
    limits: torch.Tensor | np.ndarray,
    dof_names: Sequence[str],
    k: int = 12,
    seed: int = 0,
    iters: int = 200,
    tol: float = 1e-5,
    reg: float = 1e-3,
    meta: dict[str, Any] | None = None,
) -> PosePrior:
    """Fit a full-covariance Gaussian mixture to unconstrained pose values by EM (float64 numpy).

    Values are first clipped to ``|x| <= X_CLIP`` (``+-inf`` included). Initialisation is k-means++
    (seeded) refined by a few Lloyd steps; EM then runs until the mean log-likelihood per frame
    improves by less than ``tol`` or ``iters`` iterations. ``reg * I`` is added to every covariance;
    a component with less than one frame's worth of responsibility is restarted at a random frame.

    Args:
        x: (N, D) unconstrained pose values (e.g. :func:`unconstrained_from_angles` of mocap angles).
        limits: (D, 2) ``[theta_min, theta_max]`` in radians, stored in the prior for Eq. 6.
        dof_names: the D atom names.
        k: number of components, >= 1; needs ``N >= 10 * k``.
        seed: seed of the initialisation and of component restarts.
        iters: maximum number of EM iterations, >= 1.
        tol: convergence threshold on the mean log-likelihood (nats per frame).
        reg: covariance regulariser, > 0 (also keeps components on repeated frames non-singular).
        meta: JSON-serialisable provenance stored in the prior; fit settings are added under ``"fit"``.

    Returns:
        The fitted :class:`PosePrior` (float64 buffers).

    Raises:
        ValueError: for input of the wrong shape, NaN values, too few frames or bad settings.
    """
    x = np.asarray(x, dtype=np.float64)
    lim = _as_float64(limits)
    if lim.ndim != 2 or lim.shape[1] != 2:
        raise ValueError(f"limits must be (D, 2), got {lim.shape}")
    d = lim.shape[0]
    if x.ndim != 2 or x.shape[1] != d:
        raise ValueError(f"x must be (N, {d}) to match limits, got {x.shape}")
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise ValueError(f"k must be a positive int, got {k!r}")
    if isinstance(iters, bool) or not isinstance(iters, int) or iters < 1:
        raise ValueError(f"iters must be a positive int, got {iters!r}")
    if not reg > 0.0:
        raise ValueError(f"reg must be > 0, got {reg!r}")
    n = x.shape[0]
    if n < 10 * k:
        raise ValueError(f"x has {n} frames; fitting k = {k} components needs at least {10 * k}")
    if np.isnan(x).any():
        raise ValueError("x has NaN values")
    x = np.clip(x, -X_CLIP, X_CLIP)  # also maps the +-inf of angles exactly on a limit to +-X_CLIP
    x1 = np.hstack([x, np.ones((n, 1))])  # (N, D + 1), see _e_step

    rng = np.random.default_rng(seed)
    global_cov = np.cov(x, rowvar=False).reshape(d, d)
    labels = _kmeans_init(x, k, rng)
    resp = np.zeros((n, k))
    resp[np.arange(n), labels] = 1.0
    weights, means, chols, n_restarts = _m_step(x, resp, reg, rng, global_cov)

    prev = -np.inf
    converged = False
    n_iter = 0
    while n_iter < iters:
        n_iter += 1
        resp, ll = _e_step(x1, weights, means, chols)
        mean_ll = float(ll.mean())
        if mean_ll - prev < tol:
            converged = True
            break
        prev = mean_ll
        weights, means, chols, restarted = _m_step(x, resp, reg, rng, global_cov)
        if restarted:
            n_restarts += restarted
            prev = -np.inf  # a restart may lower the likelihood; do not take that for convergence
    if not converged:
        mean_ll = float(_e_step(x1, weights, means, chols)[1].mean())

    fit_info = {
        "k": k,
        "seed": seed,
        "n_frames": n,
        "iterations": n_iter,
        "converged": converged,
        "mean_log_likelihood": mean_ll,
        "restarts": n_restarts,
        "reg": reg,
        "tol": tol,
        "x_clip": X_CLIP,
        "clipped_fraction": float((np.abs(x) >= X_CLIP).mean()),
    }
    return PosePrior(weights, means, chols, lim, dof_names, meta={**(meta or {}), "fit": fit_info})
