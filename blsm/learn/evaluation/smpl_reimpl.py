"""SMPL-reimpl: the SMPL-type baseline of thesis Sec. 5.5.1.

Same topology, kinematic tree, bind frames, DoF table (Eq. 5.6) and blend weights as the BLSM it is
compared with, but no bone scaling (every s = 1 in Eq. 5.3) and SMPL's way of modelling shape:

- shape is a PCA of T-pose meshes, ``T(c) = T_mean + c P`` (P per standard deviation);
- bind-pose joints are regressed from the shaped T-pose, ``J(c) = R T(c)``, with a joint
  regressor R (J, V) that is sparse, non-negative and has rows summing to 1;
- posing is LBS (Eq. 5.12) with those joints as bind-pose heads
  (:func:`blsm.learn.posing.pose` with ``bone_scales = 1`` and ``heads = J(c)``).

Training (:func:`train_smpl_reimpl`), on registrations S^n in the template topology:

1. Pose and per-body skeleton of every registration: staged fit (Sec. 5.5.2) of the BLSM skeleton
   with 20 free per-bone scales b (log-parametrised) on the mean template, i.e. Eq. 5.26 without
   the bone basis. This yields angles theta^n, R^n, t^n and the body's bind-pose joints J^n (the
   template heads moved along the chain by the scales b^n).
2. Un-posing: T^n = LBS^{-1}(S^n) per vertex (:func:`blsm.lbs.unskin`) with the transforms of
   (theta^n, R^n, t^n) on unscaled bones whose bind heads are J^n, so ``pose(T^n, J^n) = S^n``.
3. Shape: PCA of the per-subject mean T-pose (one per subject when subject ids are given, as SMPL
   fits one template per subject; otherwise one per registration).
4. Joint regressor: each row is initialised as the mean of the ring of vertices around the joint
   (template vertices within 1 cm of the plane through the joint normal to its bone, on the joint's
   own, parent or child bones, no farther than 2.5x the nearest vertex), restricted to a support of
   the band of +-3 cm around that plane (on the same bones, within 6x the nearest vertex distance)
   plus the 64 nearest template vertices, and then trained with Adam so that
   ``R T^n ~ J^n`` over the training registrations, each row a softmax of logits over its support
   (so it stays non-negative, sums to 1 and is zero elsewhere), plus a small pull towards the
   initial logits.

Shortcuts against SMPL: the blend weights are not retrained (they are the BLSM's), there are no
pose-corrective blendshapes (the thesis removes them too), and step 1 is not alternated with 2-4.

File format ``blsm-smpl-reimpl`` v1 (``.npz``): ``template`` (V, 3) float32 metres,
``shape_basis`` (K, V, 3) float32 metres per standard deviation, ``joint_regressor`` (J, V) float32,
``meta_json`` (bone names, training summary).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from blsm.io import read_versioned_npz, write_versioned_npz
from blsm.learn.evaluation.fit import FitConfig, Fittable, staged_fit
from blsm.learn.posing import Posed, pose

pose_fn = pose  # ``forward`` has an argument named ``pose``
from blsm.lbs import unskin

FORMAT = "blsm-smpl-reimpl"
FORMAT_VERSION = 1


def regress_joints(regressor: torch.Tensor, template: torch.Tensor) -> torch.Tensor:
    """``J = R T``: (J, V) x (B, V, 3) -> (B, J, 3) bind-pose joints in metres."""
    return torch.einsum("jv,bvc->bjc", regressor, template)


def rest_joints(skeleton: nn.Module, bone_scales: torch.Tensor) -> torch.Tensor:
    """Bind-pose joints of a BLSM skeleton with global bone scales b (Eqs. 5.3-5.5, no rotation).

    Args:
        skeleton: a :class:`blsm.BLSM`.
        bone_scales: (B, J) global scales b.

    Returns:
        (B, J, 3) joints in metres: the root stays, each offset to a child scales with the parent's b.
    """
    heads = skeleton.heads.to(bone_scales.dtype)
    par = skeleton.parents_t.clamp(min=0)
    scaled = bone_scales[:, par, None] * (heads - heads[par])  # (B, J, 3)
    return heads[0] + torch.einsum("jk,bkc->bjc", skeleton.chain.to(bone_scales.dtype), scaled)


class SMPLReimpl(nn.Module):
    """The baseline model: PCA T-pose shape, regressed joints, BLSM skeleton without scaling."""

    def __init__(
        self,
        skeleton: nn.Module,
        template: torch.Tensor,
        shape_basis: torch.Tensor,
        joint_regressor: torch.Tensor,
        meta: dict | None = None,
    ) -> None:
        super().__init__()
        v, j = skeleton.num_vertices, skeleton.num_joints
        if tuple(template.shape) != (v, 3):
            raise ValueError(f"template must be ({v}, 3), got {tuple(template.shape)}")
        if shape_basis.dim() != 3 or tuple(shape_basis.shape[1:]) != (v, 3):
            raise ValueError(f"shape_basis must be (K, {v}, 3), got {tuple(shape_basis.shape)}")
        if tuple(joint_regressor.shape) != (j, v):
            raise ValueError(f"joint_regressor must be ({j}, {v}), got {tuple(joint_regressor.shape)}")
        self.skeleton = skeleton
        self.meta = dict(meta or {})
        dtype = skeleton.template.dtype
        self.register_buffer("template", template.to(dtype))
        self.register_buffer("shape_basis", shape_basis.to(dtype))
        self.register_buffer("joint_regressor", joint_regressor.to(dtype))

    @property
    def num_coeffs(self) -> int:
        return int(self.shape_basis.shape[0])

    def rest(self, shape: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Shaped T-pose and its joints.

        Args:
            shape: (B, K) PCA coefficients (standard deviations), or None for the mean.

        Returns:
            template (B, V, 3) and joints (B, J, 3), metres.
        """
        if shape is None:
            tmpl = self.template[None]
        else:
            if shape.dim() != 2 or shape.shape[1] != self.num_coeffs:
                raise ValueError(f"shape must be (B, {self.num_coeffs}), got {tuple(shape.shape)}")
            tmpl = self.template + torch.einsum("bk,kvc->bvc", shape, self.shape_basis)
        return tmpl, regress_joints(self.joint_regressor, tmpl)

    def forward(
        self,
        shape: torch.Tensor | None = None,
        pose: torch.Tensor | None = None,
        angles: torch.Tensor | None = None,
        global_orient: torch.Tensor | None = None,
        transl: torch.Tensor | None = None,
    ) -> Posed:
        """Shape and pose the baseline.

        Args:
            shape: (B, K) shape coefficients.
            pose: (B, 47) unconstrained atoms (Eq. 5.6), or ``angles`` (B, 47) radians.
            global_orient: (B, 3) axis-angle about the root joint; transl: (B, 3) metres.

        Returns:
            :class:`blsm.learn.posing.Posed` (``vertices`` (B, V, 3), ``joints`` (B, J, 3), ...).
        """
        for name, t in (("pose", pose), ("angles", angles)):
            if t is not None and (t.dim() != 2 or t.shape[1] != self.skeleton.num_dofs):
                raise ValueError(f"{name} must be (B, {self.skeleton.num_dofs}), got {tuple(t.shape)}")
        tmpl, joints = self.rest(shape)
        batch = max(x.shape[0] for x in (tmpl, pose, angles, global_orient, transl) if x is not None)
        ones = torch.ones(batch, self.skeleton.num_joints, dtype=tmpl.dtype, device=tmpl.device)
        return pose_fn(
            self.skeleton, tmpl.expand(batch, -1, -1), bone_scales=ones, pose=pose, angles=angles,
            global_orient=global_orient, transl=transl, heads=joints.expand(batch, -1, -1),
        )

    def save(self, path: str | Path) -> Path:
        """Write the ``blsm-smpl-reimpl`` ``.npz`` atomically."""
        meta = {**self.meta, "bone_names": list(self.skeleton.bone_names)}
        return write_versioned_npz(path, FORMAT, FORMAT_VERSION, {
            "template": self.template.detach().cpu().float().numpy(),
            "shape_basis": self.shape_basis.detach().cpu().float().numpy(),
            "joint_regressor": self.joint_regressor.detach().cpu().float().numpy(),
            "meta_json": np.array(json.dumps(meta)),
        })


def load_smpl_reimpl(path: str | Path, skeleton: nn.Module | None = None) -> SMPLReimpl:
    """Read a ``blsm-smpl-reimpl`` file; ``skeleton`` defaults to the packaged BLSM."""
    import blsm

    path = Path(path)
    arrays = read_versioned_npz(path, FORMAT, FORMAT_VERSION, "SMPL-reimpl")
    for key in ("template", "shape_basis", "joint_regressor", "meta_json"):
        if key not in arrays:
            raise ValueError(f"{path}: missing array {key!r}")
    skeleton = skeleton if skeleton is not None else blsm.load()
    meta = json.loads(str(arrays["meta_json"]))
    if meta.get("bone_names") != list(skeleton.bone_names):
        raise ValueError(f"{path}: bone names differ from the skeleton's")
    try:
        return SMPLReimpl(
            skeleton,
            torch.from_numpy(arrays["template"]),
            torch.from_numpy(arrays["shape_basis"]),
            torch.from_numpy(arrays["joint_regressor"]),
            meta,
        )
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc


class SMPLReimplFittable(Fittable):
    """:class:`SMPLReimpl` for :func:`blsm.learn.evaluation.fit.staged_fit`: one group ``shape``."""

    def __init__(self, model: SMPLReimpl) -> None:
        self.model = model
        self.skeleton = model.skeleton
        self.coeff_sizes = {"shape": model.num_coeffs}

    def vertices(self, params: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.model(
            shape=params["shape"], pose=params["pose"], global_orient=params["global_orient"],
            transl=params["transl"],
        ).vertices


class FreeScaleFittable(Fittable):
    """The mean BLSM template on a skeleton with 20 free bone scales ``b = b_mean exp(l)``.

    Eq. 5.26 without a bone basis: the group ``log_scale`` (J) replaces c_b.
    """

    def __init__(self, skeleton: nn.Module) -> None:
        self.skeleton = skeleton
        self.coeff_sizes = {"log_scale": skeleton.num_joints}

    def bone_scales(self, params: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.skeleton.bone_mean * torch.exp(params["log_scale"])

    def vertices(self, params: dict[str, torch.Tensor]) -> torch.Tensor:
        return pose(
            self.skeleton, self.skeleton.template, bone_scales=self.bone_scales(params),
            pose=params["pose"], global_orient=params["global_orient"], transl=params["transl"],
        ).vertices


def ring_regressor(
    skeleton: nn.Module, slab: float = 0.01, support: int = 64
) -> tuple[torch.Tensor, torch.Tensor]:
    """Initial joint regressor (mean of the ring of vertices around each joint) and its support.

    Args:
        skeleton: a :class:`blsm.BLSM`.
        slab: half thickness in metres of the slab normal to the bone through the joint.
        support: number of nearest template vertices added to the trainable support, which is
            otherwise the band of 3 slab half-widths around the ring within 6x the nearest-vertex
            distance (a full cross-section, so the
            joint can sit inside the convex hull of its support).

    Returns:
        regressor (J, V) with rows summing to 1, and a boolean support mask (J, V).
    """
    v = skeleton.template.double()
    heads = skeleton.heads.double()
    parents = skeleton.parents
    nj, nv = len(parents), v.shape[0]
    reg = torch.zeros(nj, nv, dtype=torch.float64)
    mask = torch.zeros(nj, nv, dtype=torch.bool)
    vb = skeleton.vertex_bones
    for j in range(nj):
        bones = {j, *(k for k, p in enumerate(parents) if p == j)}
        if parents[j] >= 0:
            bones.add(parents[j])
        rel = v - heads[j]
        dist = rel.norm(dim=1)
        axis = skeleton.frames[j, :, 1].double()  # y runs along the bone
        near = torch.isin(vb, torch.tensor(sorted(bones)))
        dmin = dist[near].min()
        ring = near & ((rel @ axis).abs() < slab) & (dist < 2.5 * dmin)
        if int(ring.sum()) < 3:
            ring = torch.zeros(nv, dtype=torch.bool)
            ring[dist.topk(8, largest=False).indices] = True
        reg[j, ring] = 1.0 / float(ring.sum())
        band = near & ((rel @ axis).abs() < 3 * slab) & (dist < 6.0 * dmin)
        mask[j, ring | band] = True
        mask[j, dist.topk(support, largest=False).indices] = True
    return reg.to(skeleton.template.dtype), mask


def _rows(logits: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Row-wise softmax over the support: >= 0, rows sum to 1, exactly 0 off the support."""
    return torch.softmax(logits.masked_fill(~mask, float("-inf")), dim=1)


def train_regressor(
    init: torch.Tensor,
    mask: torch.Tensor,
    templates: torch.Tensor,
    joints: torch.Tensor,
    steps: int = 300,
    lr: float = 0.05,
    pull: float = 1e-4,
    off_ring: float = -8.0,
) -> torch.Tensor:
    """Fit a non-negative, sparse, row-stochastic joint regressor to ``R T^n ~ J^n``.

    Rows are a softmax of logits over the support (SMPL solves a non-negative least squares with
    the same constraints); the logits start at 0 on the ring and ``off_ring`` elsewhere, so the
    first iterate is the ring mean up to ``exp(off_ring)`` per support vertex, and Adam (whose
    steps do not shrink with the tiny softmax gradients) can still move weight onto them.

    Args:
        init: (J, V) initial regressor (the ring means; its non-zero entries are the ring).
        mask: (J, V) bool support.
        templates: (N, V, 3) un-posed training meshes T^n, metres.
        joints: (N, J, 3) their bind-pose joints J^n, metres.
        steps, lr: Adam steps and learning rate.
        pull: weight of ``||logits - logits_init||^2`` (keeps rows near the ring when data are scarce).
        off_ring: initial logit of the support vertices off the ring.

    Returns:
        (J, V) regressor, >= 0, rows summing to 1, zero off the support.
    """
    mask = mask | (init > 0)
    logits0 = torch.where(init > 0, torch.zeros_like(init), torch.full_like(init, off_ring))
    logits = logits0.clone().requires_grad_(True)
    opt = torch.optim.Adam([logits], lr=lr)
    for _ in range(steps):
        opt.zero_grad()
        err = regress_joints(_rows(logits, mask), templates) - joints
        loss = 1e6 * (err**2).sum(-1).mean() + pull * ((logits - logits0) ** 2 * mask).sum()
        loss.backward()
        opt.step()
    with torch.no_grad():
        return _rows(logits, mask)


@dataclass
class SMPLTrainConfig:
    """Settings of :func:`train_smpl_reimpl`.

    Attributes:
        fit: staged-fit settings for the pose / bone-scale estimation of step 1.
        regressor_steps: Adam steps of the joint-regressor fit (0 keeps the ring initialisation).
        regressor_lr: its learning rate.
    """

    fit: FitConfig | None = None
    regressor_steps: int = 300
    regressor_lr: float = 0.05


def train_smpl_reimpl(
    blsm_model: nn.Module,
    registrations: torch.Tensor,
    num_coeffs: int,
    subjects: list[str] | None = None,
    config: SMPLTrainConfig | None = None,
) -> SMPLReimpl:
    """Train the baseline on registrations (steps 1-4 of the module docstring).

    Args:
        blsm_model: the BLSM whose topology, skeleton, DoF table and blend weights are shared.
        registrations: (N, V, 3) registered meshes S^n, posed, world frame, metres.
        num_coeffs: number of PCA shape components K kept (capped at subjects - 1).
        subjects: optional (N,) subject id per registration; T-poses are averaged per subject.
        config: :class:`SMPLTrainConfig`.

    Returns:
        A trained :class:`SMPLReimpl` (in ``blsm_model``'s dtype).
    """
    cfg = config or SMPLTrainConfig()
    if registrations.dim() != 3 or registrations.shape[1:] != blsm_model.template.shape:
        raise ValueError(
            f"registrations must be (N, {blsm_model.num_vertices}, 3), got {tuple(registrations.shape)}"
        )
    n = registrations.shape[0]
    if subjects is not None and len(subjects) != n:
        raise ValueError(f"subjects has {len(subjects)} ids for {n} registrations")
    if n < 2 or num_coeffs < 1:
        raise ValueError(f"need >= 2 registrations and num_coeffs >= 1, got {n} and {num_coeffs}")
    t0 = time.time()
    dtype = blsm_model.template.dtype
    regs = registrations.to(dtype)

    # 1. pose and per-body bone scales (Eq. 5.26 with free scales)
    free = FreeScaleFittable(blsm_model)
    fit = staged_fit(free, regs, config=cfg.fit)
    b = free.bone_scales(fit.params)
    joints = rest_joints(blsm_model, b)  # (N, J, 3)

    # 2. un-pose on unscaled bones whose bind heads are the body's joints
    with torch.no_grad():
        ones = torch.ones_like(b)
        posed = pose(blsm_model, blsm_model.template, bone_scales=ones, pose=fit.params["pose"],
                     global_orient=fit.params["global_orient"], transl=fit.params["transl"], heads=joints)
        tposes = unskin(regs, blsm_model.weights, posed.transforms)  # (N, V, 3)

    # 3. PCA of per-subject T-poses
    if subjects is not None:
        ids = sorted(set(subjects))
        per = torch.stack([tposes[[i for i, s in enumerate(subjects) if s == sid]].mean(0) for sid in ids])
    else:
        per = tposes
    mean = per.mean(0)
    centred = (per - mean).reshape(per.shape[0], -1).double()
    k = min(num_coeffs, per.shape[0] - 1)
    _, svals, vt = torch.linalg.svd(centred, full_matrices=False)
    std = svals[:k] / max(per.shape[0] - 1, 1) ** 0.5
    basis = (std[:, None] * vt[:k]).reshape(k, -1, 3).to(dtype)
    explained = (svals[:k] ** 2).sum() / (svals**2).sum().clamp(min=1e-30)

    # 4. joint regressor: ring initialisation, then R T^n ~ J^n
    init, mask = ring_regressor(blsm_model)
    reg = (
        train_regressor(init.double(), mask, tposes.double(), joints.double(),
                        steps=cfg.regressor_steps, lr=cfg.regressor_lr).to(dtype)
        if cfg.regressor_steps > 0 else init
    )
    with torch.no_grad():
        j_err_init = (regress_joints(init.to(dtype), tposes) - joints).norm(dim=-1).mean()
        j_err = (regress_joints(reg, tposes) - joints).norm(dim=-1).mean()
    meta = {
        "num_registrations": n,
        "num_subjects": int(per.shape[0]),
        "num_coeffs": k,
        "explained_variance": float(explained),
        "pose_fit_error_mm": float(fit.mean_error.mean() * 1000),
        "joint_regressor_error_mm": {"ring_init": float(j_err_init * 1000), "trained": float(j_err * 1000)},
        "seconds": round(time.time() - t0, 2),
    }
    return SMPLReimpl(blsm_model, mean, basis, reg, meta)
