"""Evaluating a reparameterised model as thesis Sec. 3.4 does, and the posed check of Sec. 3.4.2.

- :func:`compactness`: the fraction of a shape space's variance in its first k components (Fig. 3.2).
- :func:`generalisation`: held-out instances projected on the first k components, mean per-vertex
  error in mm (Fig. 3.3).
- :func:`specificity`: random samples of the first k components, each one's mean per-vertex distance
  in mm to its nearest held-out instance, averaged (Fig. 3.4).
- :func:`tpose_instances`: held-out bodies brought to the model's T-pose frame as ``blsm learn``
  does (Eq. 5.26 fit of pose, bone and shape coefficients, then the exact per-vertex inverse of LBS),
  minus the bone correctives ``c_b P_bc``: what the shape space ``V_mean + c_s P_s`` models.
- :func:`posed_check`: both models posed with the same random plausible poses (the CMU pose prior)
  and coefficients; the new posed vertices against ``W'`` times the old posed ones.

The thesis scales its meshes into a box of diagonal 1; here errors are in millimetres on bodies in
metres. Shape spaces are :class:`blsm.learn.reparam.mapping.ShapeSpace` (principal axes).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp
import torch

from blsm.learn.reparam.mapping import ShapeSpace


def _flat(space: ShapeSpace, k: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(mean (3N,), orthonormal axes (k, 3N), std (k,)) of the first k components, float64."""
    comps = torch.as_tensor(space.components[:k], dtype=torch.float64).reshape(k, -1)
    std = torch.as_tensor(space.variances[:k], dtype=torch.float64).sqrt()
    return torch.as_tensor(space.mean, dtype=torch.float64).reshape(-1), comps / std[:, None], std


def compactness(space: ShapeSpace) -> np.ndarray:
    """(K,) cumulative fraction of the space's variance in its first 1..K components (Fig. 3.2)."""
    v = np.asarray(space.variances, dtype=np.float64)
    return np.cumsum(v) / v.sum()


def data_compactness(space: ShapeSpace, instances: np.ndarray, ks: Sequence[int]) -> np.ndarray:
    """(len(ks),) fraction of the instances' squared deviation from the mean in the first k axes."""
    mean, axes, _ = _flat(space, max(ks))
    x = torch.as_tensor(instances, dtype=torch.float64).reshape(len(instances), -1) - mean
    proj = (x @ axes.T).pow(2).sum(0)  # (K,)
    total = x.pow(2).sum()
    return np.array([float(proj[:k].sum() / total) for k in ks])


def per_vertex_mm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean per-vertex Euclidean distance in mm between (..., 3N) flattened meshes."""
    d = (a - b).reshape(*a.shape[:-1], -1, 3)
    return d.norm(dim=-1).mean(-1) * 1000.0


def _resampler(resample: sp.spmatrix | None, device: str):
    """(B, 3N1) -> (B, 3N2): W' applied to flattened meshes (identity when ``resample`` is None)."""
    if resample is None:
        return lambda y: y
    w = resample.tocoo()
    wt = torch.sparse_coo_tensor(np.stack([w.row, w.col]), w.data, w.shape, dtype=torch.float64, device=device)

    def apply(y: torch.Tensor) -> torch.Tensor:
        n1 = w.shape[1]
        flat = y.double().reshape(len(y), n1, 3).permute(1, 0, 2).reshape(n1, -1)  # (N1, B*3)
        return (wt @ flat).reshape(w.shape[0], len(y), 3).permute(1, 0, 2).reshape(len(y), -1).to(y.dtype)

    return apply


def generalisation(
    space: ShapeSpace, instances: np.ndarray, ks: Sequence[int], resample: sp.spmatrix | None = None
) -> np.ndarray:
    """(len(ks),) mean over instances of the per-vertex error (mm) of their projection (Fig. 3.3).

    Args:
        space: the shape space (principal axes).
        instances: (N, V, 3) held-out bodies in the space's topology and frame, metres.
        ks: numbers of components.
        resample: W' (N2, V): measure the error at the points W' picks (the new topology's
            vertices) instead of at the space's own vertices; None for the own vertices.
    """
    mean, axes, _ = _flat(space, max(ks))
    x = torch.as_tensor(instances, dtype=torch.float64).reshape(len(instances), -1) - mean
    c = x @ axes.T  # (N, K)
    at = _resampler(resample, "cpu")
    return np.array([float(per_vertex_mm(at(c[:, :k] @ axes[:k] - x), torch.zeros(1)).mean()) for k in ks])


def specificity(
    space: ShapeSpace, instances: np.ndarray, ks: Sequence[int], samples: int = 1000, seed: int = 0,
    chunk: int = 16, resample: sp.spmatrix | None = None, device: str = "cpu",
) -> np.ndarray:
    """(len(ks),) mean over random samples of the distance (mm) to the nearest instance (Fig. 3.4).

    Each sample draws the first k coefficients from N(0, 1) (the same draws for every space given
    the same seed); its distance to an instance is the mean per-vertex Euclidean distance, at the
    points ``resample`` picks when given (as :func:`generalisation`). ``device``: where the
    distances are computed (``cuda`` for speed; the result does not depend on it beyond round-off).
    """
    mean, axes, std = (t.to(device) for t in _flat(space, max(ks)))
    at = _resampler(resample, device)
    x = at(torch.as_tensor(instances, dtype=torch.float64, device=device).reshape(len(instances), -1)).float()
    z = torch.randn(samples, max(ks), generator=torch.Generator().manual_seed(seed), dtype=torch.float64).to(device)
    out = []
    for k in ks:
        total = 0.0
        for s in range(0, samples, chunk):
            y = at(mean + (z[s : s + chunk, :k] * std[:k]) @ axes[:k]).float()  # (c, 3N)
            d = per_vertex_mm(y[:, None], x[None])  # (c, N)
            total += float(d.min(1).values.sum())
        out.append(total / samples)
    return np.array(out)


# ------------------------------------------------------------------------------------------------
# Held-out bodies in the T-pose frame


def learned_model(model):
    """A :class:`blsm.learn.training.train_fit.LearnedModel` holding a :class:`blsm.BLSM`'s own arrays."""
    from blsm.learn.training.train_fit import LearnedModel

    return LearnedModel(
        model.heads.float(), model.template.clone(), model.weights.clone(), model.bone_mean.clone(),
        model.bone_basis.clone(), model.bone_correctives.clone(), model.shape_decoder.basis.clone(),
    )  # fmt: skip


def tpose_instances(model, targets: torch.Tensor, init: dict[str, torch.Tensor], seed: int = 0, iterations: int = 150,
                    device: str = "cpu"):
    """Held-out posed bodies to the model's T-pose frame, bone correctives removed (as ``blsm learn``).

    Args:
        model: a :class:`blsm.BLSM` (float32, CPU).
        targets: (N, V, 3) posed bodies in the model's topology, metres.
        init: ``angles`` (N, 47), ``global_orient`` (N, 3), ``transl`` (N, 3) to start the fit from
            (the registrations' stage-1 values).
        seed: of the fit's vertex subset.
        iterations: Adam steps per round of :func:`blsm.learn.training.train_fit.fit_full`.
        device: where the fit runs (the model is moved there and back to the CPU).

    Returns:
        (instances (N, V, 3) float64 ``unskin(target) - c_b P_bc``, the fitted parameters, the fit's
        mean per-vertex error in mm).
    """
    from blsm.learn.training.train_fit import FitParams, TrainFitConfig, errors_mm, fit_full, unskinned

    model = model.to(device)
    targets = targets.float().to(device)
    mdl = learned_model(model)
    n = len(targets)
    st = FitParams(init["angles"].float().to(device), torch.zeros(n, model.num_bone_coeffs, device=device),
                   init["global_orient"].float().to(device), init["transl"].float().to(device))
    cfg = TrainFitConfig(iterations=iterations)
    st = fit_full(model, mdl, targets, st, cfg, generator=torch.Generator().manual_seed(seed))
    err = float(errors_mm(model, mdl, targets, st, cfg.batch_size).mean())
    un = unskinned(model, mdl, targets, st, cfg.batch_size).double()
    bone_part = torch.einsum("bk,kvc->bvc", st.bone.double(), mdl.correctives.double())
    model.to("cpu")
    return (un - bone_part).cpu().numpy(), st, err


# ------------------------------------------------------------------------------------------------
# Posed check (Sec. 3.4.2)


@torch.no_grad()
def posed_check(
    model1, model2, corners: np.ndarray, bary: np.ndarray, distance: np.ndarray, num: int = 32,
    seed: int = 0, coincide: float = 1e-4, coeff_map: tuple[np.ndarray, np.ndarray] | None = None,
    surface: bool = False,
) -> dict:
    """Pose both models with the same random plausible poses and coefficients and compare.

    Poses are drawn from the CMU pose prior (:mod:`blsm.mocap.prior`), bone and shape coefficients
    from N(0, 1), global orientation and translation at random. The new model's posed vertices are
    compared with ``W'`` times the old model's posed vertices, over the new vertices within
    ``coincide`` metres of the old surface ("where the surfaces coincide") and over all of them.

    Args:
        model1, model2: the original and the reparameterised :class:`blsm.BLSM`.
        corners, bary: W' (:func:`blsm.learn.reparam.model.read_correspondence`); distance: (N2,) m.
        coeff_map: (A, a) with ``c_2 = A c + a`` for a model whose shape space is Eq. 3.5's principal
            axes (``shape_space: eq35``); None when the coefficients are shared (``mapped``).
        surface: also the distance of each new posed vertex to the old posed *surface* (closest
            point; slower).

    Returns:
        max / mean distances in mm (coinciding vertices, all vertices), the number of coinciding
        vertices, and the largest joint difference in mm.
    """
    from blsm.mocap.prior import DEFAULT_PRIOR, load_prior

    g = torch.Generator().manual_seed(seed)
    pose = load_prior(DEFAULT_PRIOR).float().sample(num, generator=g)
    bone = torch.randn(num, model1.num_bone_coeffs, generator=g)
    shape = torch.randn(num, model1.num_shape_coeffs, generator=g)
    orient = torch.randn(num, 3, generator=g) * 0.5
    transl = torch.randn(num, 3, generator=g) * 0.2
    out1 = model1(pose=pose, bone=bone, shape=shape, global_orient=orient, transl=transl)
    shape2 = shape
    if coeff_map is not None:
        shape2 = shape @ torch.as_tensor(coeff_map[0], dtype=torch.float32).T + torch.as_tensor(coeff_map[1], dtype=torch.float32)
    out2 = model2(pose=pose, bone=bone, shape=shape2, global_orient=orient, transl=transl)
    ref = torch.einsum("nk,bnkc->bnc", torch.as_tensor(bary, dtype=torch.float64), out1.vertices.double()[:, corners])
    d = (out2.vertices.double() - ref).norm(dim=-1) * 1000.0  # (B, N2) mm
    on = torch.as_tensor(distance < coincide)
    res = {
        "poses": num,
        "coinciding_vertices": int(on.sum()),
        "coinciding_max_mm": float(d[:, on].max()) if on.any() else None,
        "coinciding_mean_mm": float(d[:, on].mean()) if on.any() else None,
        "all_max_mm": float(d.max()),
        "all_mean_mm": float(d.mean()),
        "joints_max_mm": float((out1.joints - out2.joints).norm(dim=-1).max() * 1000.0),
    }
    res["coinciding_within_1mm"] = float((d[:, on] < 1.0).double().mean()) if on.any() else None
    res["coinciding_p99_mm"] = float(torch.quantile(d[:, on].flatten()[::7], 0.99)) if on.any() else None
    if surface:  # distance to the old posed surface: sliding along it does not count
        from blsm.learn.reparam.mapping import closest_points

        f1 = model1.faces.numpy()
        s = np.stack([closest_points(out2.vertices[b].double().numpy(), out1.vertices[b].double().numpy(), f1).distance
                      for b in range(num)]) * 1000.0
        s = s[:, on.numpy()] if on.any() else s
        res["coinciding_surface_max_mm"], res["coinciding_surface_mean_mm"] = float(s.max()), float(s.mean())
    res["rest_offset_mean_mm"] = float(np.mean(distance) * 1000.0)  # |mu_2 - W mu_1|: the template's own offset
    return res
