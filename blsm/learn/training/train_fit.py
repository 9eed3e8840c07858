"""The per-registration fit of learning (thesis Eq. 5.26) and the model's reconstructions.

:class:`LearnedModel` is the model being learned (tensors on one device); a
:class:`FitParams` holds the pose and coefficients of N registrations.
:func:`fit_pose_and_bones` fits theta, c_b, global orientation and translation per registration
with Adam (:class:`TrainFitConfig`); :func:`fit_full` alternates it with the closed-form shape
coefficients. :mod:`blsm.learn.training.train` uses them between its steps.

Units: metres, radians; errors in millimetres.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from blsm.joint_limits import unconstrained_from_angles
from blsm.lbs import unskin
from blsm.learn.posing import pose


@dataclass
class TrainFitConfig:
    """Per-registration fit of theta, c_b (and c_s) (Eq. 5.26), Adam with a cosine-decayed rate.

    The ``train.fit`` section of a run config (not :class:`blsm.learn.evaluation.fit.FitConfig`, the staged fit
    of the evaluation).
    """

    iterations: int = 150
    lr: float = 0.02  # unconstrained pose, c_b (std units), global orientation (rad)
    transl_lr: float = 0.002  # translation (m)
    num_vertices: int = 2000  # vertices used in the fit (a fixed random subset); 0 = all
    batch_size: int = 64  # registrations per batch (memory)
    bone_prior: float = 0.01  # weight of ||c_b||^2 against the mean squared vertex error in mm^2
    shape_rounds: int = 2  # evaluation / step 5: alternations of (theta, c_b) and closed-form c_s

    def __post_init__(self) -> None:
        for name in ("iterations", "batch_size", "shape_rounds"):
            if getattr(self, name) < 1:
                raise ValueError(f"fit.{name} must be >= 1, got {getattr(self, name)}")
        if self.num_vertices < 0:
            raise ValueError(f"fit.num_vertices must be >= 0, got {self.num_vertices}")
        if self.lr <= 0 or self.transl_lr <= 0 or self.bone_prior < 0:
            raise ValueError("fit.lr and fit.transl_lr must be > 0, fit.bone_prior >= 0")


@dataclass
class LearnedModel:
    """The model being learned, as tensors on one device (float32 unless noted)."""

    heads: torch.Tensor  # (J, 3)
    template: torch.Tensor  # (V, 3) V_mean
    weights: torch.Tensor  # (V, J)
    bone_mean: torch.Tensor  # (J,)
    bone_basis: torch.Tensor  # (Kb, J)
    correctives: torch.Tensor  # (Kb, V, 3)
    shape_basis: torch.Tensor | None = None  # (Ks, V, 3)


@dataclass
class FitParams:
    """Per-registration parameters (N registrations)."""

    angles: torch.Tensor  # (N, 47) radians
    bone: torch.Tensor  # (N, Kb) c_b
    global_orient: torch.Tensor  # (N, 3)
    transl: torch.Tensor  # (N, 3)
    shape: torch.Tensor | None = None  # (N, Ks) c_s

    def take(self, idx: torch.Tensor | slice) -> FitParams:
        return FitParams(
            self.angles[idx], self.bone[idx], self.global_orient[idx], self.transl[idx],
            None if self.shape is None else self.shape[idx],
        )  # fmt: skip


def templates(
    mdl: LearnedModel, st: FitParams, idx: torch.Tensor | None, base: torch.Tensor | None
) -> torch.Tensor:
    """Person templates ``V_mean + c_b P_bc + c_s P_s`` (+ fixed ``base`` offsets) on vertices idx."""
    sel = slice(None) if idx is None else idx
    t = mdl.template[sel].expand(st.bone.shape[0], -1, -1)
    t = t + torch.einsum("bk,kvc->bvc", st.bone, mdl.correctives[:, sel])
    if st.shape is not None and mdl.shape_basis is not None:
        t = t + torch.einsum("bk,kvc->bvc", st.shape, mdl.shape_basis[:, sel])
    if base is not None:
        t = t + base[:, sel]
    return t


def posed_model(model, mdl: LearnedModel, st: FitParams, idx=None, base=None, weights=None, x=None):
    """The learned model posed with ``st`` (:func:`blsm.learn.posing.pose`), on vertices ``idx``,
    with bone scales ``b_mean + c_b P_b`` (Eq. 5.4); ``x`` (N, 47) unconstrained atoms replace the
    angles of ``st`` where given, ``weights`` (V, J) the model's."""
    w = mdl.weights if weights is None else weights
    sel = slice(None) if idx is None else idx
    b = mdl.bone_mean + st.bone @ mdl.bone_basis  # Eq. 5.4
    kw = dict(pose=x) if x is not None else dict(angles=st.angles)
    return pose(
        model, templates(mdl, st, idx, base), bone_scales=b, global_orient=st.global_orient,
        transl=st.transl, weights=w[sel], heads=mdl.heads, **kw,
    )  # fmt: skip


def fit_pose_and_bones(
    model,
    mdl: LearnedModel,
    targets: torch.Tensor,
    init: FitParams,
    cfg: TrainFitConfig,
    fit_bones: bool = True,
    base: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
) -> FitParams:
    """Eq. 5.26: theta, c_b, global orientation and translation per registration (Adam, batched).

    The loss of each registration is its mean squared vertex distance in mm^2 (on a fixed random
    subset of ``cfg.num_vertices`` vertices) plus ``cfg.bone_prior * ||c_b||^2``; the batch loss is their sum,
    so registrations do not interact. c_s (if any) and ``base`` offsets (N, V, 3) stay fixed.
    """
    n, v = targets.shape[:2]
    idx = None
    if 0 < cfg.num_vertices < v:
        idx = torch.randperm(v, generator=generator)[: cfg.num_vertices].to(targets.device)
    out = []
    for s in range(0, n, cfg.batch_size):
        sl = slice(s, min(n, s + cfg.batch_size))
        st = init.take(sl)
        tgt = targets[sl] if idx is None else targets[sl][:, idx]
        bse = None if base is None else base[sl]
        x = unconstrained_from_angles(st.angles, model.dof_limits, eps=1e-4).detach().requires_grad_(True)
        cb = st.bone.detach().clone().requires_grad_(fit_bones)
        go = st.global_orient.detach().clone().requires_grad_(True)
        tr = st.transl.detach().clone().requires_grad_(True)
        groups = [{"params": [x, go], "lr": cfg.lr}, {"params": [tr], "lr": cfg.transl_lr}]
        if fit_bones:
            groups.append({"params": [cb], "lr": cfg.lr})
        opt = torch.optim.Adam(groups)
        base_lrs = [g["lr"] for g in opt.param_groups]
        for it in range(cfg.iterations):
            scale = 0.5 * (1.0 + math.cos(math.pi * it / cfg.iterations))
            for g, lr0 in zip(opt.param_groups, base_lrs):
                g["lr"] = lr0 * max(scale, 0.02)
            cur = FitParams(st.angles, cb, go, tr, st.shape)
            pv = posed_model(model, mdl, cur, idx, bse, x=x).vertices
            sq = (pv - tgt).pow(2).sum(-1).mean(-1) * 1e6  # (B,) mean squared distance, mm^2
            loss = sq.sum() + cfg.bone_prior * cb.pow(2).sum()
            if not torch.isfinite(loss):
                raise FloatingPointError("non-finite loss while fitting pose and bone coefficients")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        with torch.no_grad():
            theta = pose(model, mdl.template[:1], pose=x).angles
        out.append(FitParams(theta.detach(), cb.detach(), go.detach(), tr.detach(), st.shape))
    return FitParams(
        torch.cat([o.angles for o in out]), torch.cat([o.bone for o in out]),
        torch.cat([o.global_orient for o in out]), torch.cat([o.transl for o in out]), init.shape,
    )  # fmt: skip


@torch.no_grad()
def unskinned(
    model, mdl: LearnedModel, targets: torch.Tensor, st: FitParams, batch: int
) -> torch.Tensor:
    """T-pose positions of the registrations (inverse of Eq. 5.12 per vertex), (N, V, 3)."""
    out = []
    for s in range(0, targets.shape[0], batch):
        sub = st.take(slice(s, s + batch))
        tr = posed_model(model, mdl, sub, idx=torch.arange(1, device=targets.device)).transforms
        out.append(unskin(targets[s : s + batch], mdl.weights, tr))
    return torch.cat(out)


@torch.no_grad()
def fit_shape(model, mdl: LearnedModel, targets: torch.Tensor, st: FitParams, batch: int) -> torch.Tensor:
    """Closed-form c_s: least squares of the un-skinned residual on P_s (Eq. 5.28 projected)."""
    no_shape = FitParams(st.angles, st.bone, st.global_orient, st.transl)
    resid = unskinned(model, mdl, targets, st, batch) - templates(mdl, no_shape, None, None)
    basis = mdl.shape_basis.reshape(mdl.shape_basis.shape[0], -1).double()
    gram = basis @ basis.T + 1e-10 * torch.eye(basis.shape[0], dtype=basis.dtype, device=basis.device)
    return torch.linalg.solve(gram, basis @ resid.reshape(len(resid), -1).double().T).T.to(targets.dtype)


@torch.no_grad()
def errors_mm(
    model, mdl: LearnedModel, targets: torch.Tensor, st: FitParams, batch: int, base=None, weights=None
) -> torch.Tensor:
    """(N,) mean per-vertex distance in mm between the model reconstruction and the targets."""
    out = []
    for s in range(0, targets.shape[0], batch):
        sl = slice(s, s + batch)
        bse = None if base is None else base[sl]
        pv = posed_model(model, mdl, st.take(sl), base=bse, weights=weights).vertices
        out.append((pv - targets[sl]).norm(dim=-1).mean(-1) * 1000.0)
    return torch.cat(out)


def fit_full(
    model, mdl: LearnedModel, targets: torch.Tensor, init: FitParams, cfg: TrainFitConfig, generator=None
) -> FitParams:
    """Fit theta, c_b and (if the model has a shape basis) c_s, alternating Adam and closed form."""
    st = init
    if mdl.shape_basis is not None and st.shape is None:
        zeros = torch.zeros(len(targets), mdl.shape_basis.shape[0], device=targets.device)
        st = dataclasses.replace(st, shape=zeros)
    rounds = cfg.shape_rounds if mdl.shape_basis is not None else 1
    for _ in range(rounds):
        st = fit_pose_and_bones(model, mdl, targets, st, cfg, generator=generator)
        if mdl.shape_basis is not None:
            st = dataclasses.replace(st, shape=fit_shape(model, mdl, targets, st, cfg.batch_size))
    return st
