"""Learning the BLSM parameters from registrations (thesis Sec. 5.4.2-5.4.4, Eqs. 5.26-5.31).

Input: an initial model (the packaged one: template V_T, skeleton, blend weights) and registrations
S^n in the template's topology from the scan registration (Eqs. 5.13-5.25), each with its stage-1
bone scales b, angles, global orientation and translation. :func:`learn_model` runs:

1. **Bone basis** (Sec. 5.4.2). Bone lengths of every rest-pose training registration are its
   fitted global bone scales times the template's bone lengths (a bone's length is the RMS distance
   from its head to its children's heads, or to its tip keypoint for a leaf; a bone's scale b_j
   scales exactly those offsets). Each body's lengths are averaged with its mirror image (left and
   right bones swapped), so the basis is symmetric. PCA on the lengths in metres; mean and basis are
   divided by the mean length of each bone, giving ``b_mean`` = 1 and ``P_b`` in scale per standard
   deviation (coefficients c_b are in standard deviations). With ``bone.rebase_skeleton`` (default)
   the bind skeleton and template are moved to the mean lengths (joints and template posed with the
   mean scales at zero pose), which keeps b_mean = 1 exact; without it the initial skeleton is kept
   and ``b_mean`` = mean length / template length.
2. **Pose and bone coefficients** (Eq. 5.26): theta, c_b (and global orientation, translation)
   re-fitted per registration with Adam, batched, on the model ``V_mean + c_b P_bc`` posed with
   ``b = b_mean + c_b P_b``, initialised from stage 1 (c_b by projecting the stage-1 lengths on the
   basis). A small ``||c_b||^2`` term (``fit.bone_prior``) is the only prior.
3. **Bone correctives and mean template** (Eq. 5.27). For fixed theta, c_b, LBS is affine in the
   template: vertex i of registration n is ``M_ni v_i + t_ni`` with the blended transform
   ``[M_ni | t_ni] = sum_j w_ij A_nj``. Eq. 5.27 is then, per vertex, a linear least-squares problem
   in the 3 (Kb + 1) unknowns ``(v_mean_i, P_bc[:, i])`` whose normal equations
   ``sum_n (a_n a_n^T) (x) M_ni^T M_ni`` with ``a_n = [1, c_b^n]`` are accumulated over the
   registrations and solved exactly (float64, plus a ridge ``correctives.ridge * N`` on P_bc). This
   is the minimiser of the *posed* residual of Eq. 5.27 itself, not of the un-skinned residual
   (the two differ because ``M_ni`` blends rotations times scales and is not a similarity).
   Steps 2 and 3 alternate ``correctives.alternations`` times.
4. **Shape basis** (Eqs. 5.28, 5.8). Residuals ``V_D = unskin(S^n) - V_mean - c_b P_bc`` in the
   T-pose frame (exact inverse of Eq. 5.12 per vertex), PCA -> P_s with ``shape.num_coeffs``
   components in metres per standard deviation; the residual mean is added to V_mean. Symmetry:
   ``shape.symmetry: symmetrize`` averages every residual with its mirror image first (all
   components symmetric, as :mod:`blsm.build_anny` does; asymmetric detail is dropped), ``augment``
   adds the mirror images as extra samples (components symmetric or antisymmetric, the shape space
   is mirror-closed).
5. **Blend weights** (Eqs. 5.30, 5.31) from the posed training registrations. Each subject's
   T-pose template is its rest-pose registration un-skinned (``V_mean + V_b + V_s + V^_D``, the
   residual V^_D being per subject, shared by its poses; a subject without a rest-pose registration
   uses ``V_mean + c_b P_bc + c_s P_s`` fitted to its first posed one); theta is re-fitted for each
   posed registration with that template and the subject's c_b, then ``W = f(W') / sum_j f(W')``,
   ``f(x) = sqrt(x^2 + eps)`` is optimised with Adam on a sparse support (each vertex's bones with
   non-zero initial weight plus their parents and children; zero elsewhere) with a pull
   ``weights.regularizer * ||W - W_0||^2`` towards the initial weights. W' is averaged with its
   mirror (``vertex_mirror``, left/right bones swapped) before f, so W is exactly symmetric.

Only rest-pose (CAESAR-like) training registrations enter steps 1-4; posed (D-FAUST-like) ones
enter step 5. Which registration is which comes from ``meta``: see :func:`is_rest_pose`.

Units: metres, radians; errors are reported in millimetres (mean per-vertex Euclidean distance).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm import io, skeleton
from blsm.config import config_from_dict
from blsm.joint_limits import unconstrained_from_angles
from blsm.lbs import linear_blend_skinning, unskin
from blsm.learn.posing import pose

LEAF_TIPS: dict[str, str] = {
    "head": "head_top",
    "wrist_l": "hand_tip_l",
    "wrist_r": "hand_tip_r",
    "ankle_l": "toe_tip_l",
    "ankle_r": "toe_tip_r",
}
"""Keypoint that ends each leaf bone (as in :mod:`blsm.build_anny`)."""

SYMMETRY_MODES = ("symmetrize", "augment")
_FLIP = (-1.0, 1.0, 1.0)


def _log(msg: str) -> None:
    print(f"[train] {msg}", file=sys.stderr, flush=True)


# ------------------------------------------------------------------------------------------------
# Configuration


@dataclass
class BoneConfig:
    """Bone-length PCA (Sec. 5.4.2)."""

    num_coeffs: int = 10
    rebase_skeleton: bool = True  # move the bind skeleton to the mean lengths (b_mean = 1 exactly)

    def __post_init__(self) -> None:
        if not 1 <= self.num_coeffs <= len(skeleton.BONE_NAMES):
            raise ValueError(f"bone.num_coeffs must be in [1, {len(skeleton.BONE_NAMES)}], got {self.num_coeffs}")


@dataclass
class FitConfig:
    """Per-registration fit of theta, c_b (and c_s) (Eq. 5.26), Adam with a cosine-decayed rate."""

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
class CorrectivesConfig:
    """Bone-corrective blendshapes and mean template (Eq. 5.27)."""

    alternations: int = 2  # rounds of (Eq. 5.26 fit, Eq. 5.27 solve)
    ridge: float = 1e-3  # ridge on P_bc, times the number of registrations

    def __post_init__(self) -> None:
        if self.alternations < 1 or self.ridge < 0:
            raise ValueError("correctives.alternations must be >= 1 and correctives.ridge >= 0")


@dataclass
class ShapeConfig:
    """Shape PCA of the T-pose residuals (Eqs. 5.28, 5.8)."""

    num_coeffs: int = 16
    symmetry: str = "symmetrize"  # symmetrize | augment

    def __post_init__(self) -> None:
        if self.num_coeffs < 1:
            raise ValueError(f"shape.num_coeffs must be >= 1, got {self.num_coeffs}")
        if self.symmetry not in SYMMETRY_MODES:
            raise ValueError(f"shape.symmetry must be one of {', '.join(SYMMETRY_MODES)}, got {self.symmetry!r}")


@dataclass
class WeightsConfig:
    """Blend-weight learning (Eqs. 5.30, 5.31)."""

    enabled: bool = True
    rounds: int = 2  # alternations of (theta, c_b re-fit with the current weights, Adam on W)
    iterations: int = 200  # Adam steps per round
    lr: float = 0.02
    eps: float = 1e-8  # f(x) = sqrt(x^2 + eps)
    batch_size: int = 16  # posed registrations per Adam step
    regularizer: float = 0.1  # weight of mean ||W - W_0||^2 per vertex against the mean squared error in mm^2
    prune_below: float = 1e-4  # final weights below this are set to 0 (then renormalised)

    def __post_init__(self) -> None:
        if self.iterations < 1 or self.batch_size < 1 or self.rounds < 1:
            raise ValueError("weights.rounds, weights.iterations and weights.batch_size must be >= 1")
        if self.lr <= 0 or self.eps <= 0 or self.regularizer < 0 or not 0 <= self.prune_below < 0.5:
            raise ValueError("weights: lr, eps must be > 0, regularizer >= 0, prune_below in [0, 0.5)")


@dataclass
class TrainConfig:
    """Everything :func:`learn_model` needs (the ``train:`` section of a YAML run config)."""

    seed: int = 0
    device: str = "cpu"
    bone: BoneConfig = field(default_factory=BoneConfig)
    fit: FitConfig = field(default_factory=FitConfig)
    correctives: CorrectivesConfig = field(default_factory=CorrectivesConfig)
    shape: ShapeConfig = field(default_factory=ShapeConfig)
    weights: WeightsConfig = field(default_factory=WeightsConfig)


OTHER_SECTIONS = ("run", "population", "registration", "evaluation")
"""Top-level sections of a run config that :func:`load_train_config` leaves to other readers."""


def load_train_config(path: str | Path) -> TrainConfig:
    """Read the ``train:`` section of a YAML run config into a :class:`TrainConfig`.

    Top-level keys other than ``train`` and :data:`OTHER_SECTIONS` are errors, as are unknown keys
    and wrong types inside ``train``; every error is one line naming the file and the key path.
    """
    path = Path(path)
    data = io.read_yaml(path, "training config")
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: (top level): expected a mapping, got {type(data).__name__}")
    known = ("train",) + OTHER_SECTIONS
    for k in data:
        if k not in known:
            raise ValueError(f"{path}: {k}: unknown key (known: {', '.join(sorted(known))})")
    return config_from_dict(TrainConfig, data.get("train"), str(path), "train")


# ------------------------------------------------------------------------------------------------
# Input and output


@dataclass
class TrainingRegistration:
    """One registration as :func:`learn_model` reads it (``blsm.learn.register.Registration`` and
    any object with these attributes work too).

    Attributes:
        vertices: (V, 3) registered mesh S^ in the model's topology, posed, world frame, metres.
        bone_scales: (J,) stage-1 global bone scales b, relative to the initial model's skeleton.
        angles: (47,) stage-1 atom angles in radians.
        global_orient: (3,) axis-angle; transl: (3,) metres.
        meta: ``subject`` (id), ``rest`` (bool) or ``pose_id``, ``split`` (train / test), ...
    """

    vertices: np.ndarray
    bone_scales: np.ndarray
    angles: np.ndarray
    global_orient: np.ndarray
    transl: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)
    displacement: np.ndarray | None = None


def is_rest_pose(meta: dict[str, Any]) -> bool:
    """Whether a registration is a subject's rest-pose (CAESAR-like) scan.

    ``meta["rest"]`` if present, else ``meta["pose_id"]`` (or ``"pose"``) in {``"rest"``, 0, ``"0"``},
    else ``meta["scan_index"] == 0`` (the first scan of a subject is its rest-pose scan).
    """
    if "rest" in meta:
        return bool(meta["rest"])
    for key in ("pose_id", "pose"):
        if key in meta:
            return meta[key] in ("rest", 0, "0")
    if "scan_index" in meta:
        return int(meta["scan_index"]) == 0
    return False


def _split(meta: dict[str, Any]) -> str:
    return str(meta.get("split") or "train")


@dataclass
class _Model:
    """The model being learned, as tensors on one device (float32 unless noted)."""

    heads: torch.Tensor  # (J, 3)
    template: torch.Tensor  # (V, 3) V_mean
    weights: torch.Tensor  # (V, J)
    bone_mean: torch.Tensor  # (J,)
    bone_basis: torch.Tensor  # (Kb, J)
    correctives: torch.Tensor  # (Kb, V, 3)
    shape_basis: torch.Tensor | None = None  # (Ks, V, 3)


@dataclass
class _State:
    """Per-registration parameters (N registrations)."""

    angles: torch.Tensor  # (N, 47) radians
    bone: torch.Tensor  # (N, Kb) c_b
    global_orient: torch.Tensor  # (N, 3)
    transl: torch.Tensor  # (N, 3)
    shape: torch.Tensor | None = None  # (N, Ks) c_s

    def take(self, idx: torch.Tensor | slice) -> _State:
        return _State(
            self.angles[idx], self.bone[idx], self.global_orient[idx], self.transl[idx],
            None if self.shape is None else self.shape[idx],
        )  # fmt: skip


# ------------------------------------------------------------------------------------------------
# Pure pieces


def bone_mirror_index(bone_names: Sequence[str]) -> list[int]:
    """Index of each bone's left/right counterpart (itself for central bones)."""
    return [list(bone_names).index(skeleton.mirror_name(n)) for n in bone_names]


def template_bone_lengths(model) -> torch.Tensor:
    """Bone lengths of a model's bind skeleton (build_anny's definition).

    A bone's length is the RMS distance from its head to its children's heads; a leaf ends at its
    tip keypoint (:data:`LEAF_TIPS`) on the template.

    Args:
        model: a :class:`blsm.BLSM`.

    Returns:
        (J,) lengths in metres.
    """
    heads, parents = model.heads, model.parents
    out = []
    for j, name in enumerate(model.bone_names):
        kids = [c for c, p in enumerate(parents) if p == j]
        if kids:
            d = heads[kids] - heads[j]
        else:
            k = model.keypoint_names.index(LEAF_TIPS[name])
            tip = (model.template[model.keypoint_vertices[k]] * model.keypoint_weights[k, :, None]).sum(0)
            d = (tip - heads[j])[None]
        out.append(d.pow(2).sum(-1).mean().sqrt())
    return torch.stack(out)


@dataclass
class BonePCA:
    """Result of :func:`bone_pca`.

    Attributes:
        mean_lengths: (J,) mean bone lengths in metres.
        directions: (Kb, J) unit principal directions in length space.
        std: (Kb,) standard deviations along them, metres.
        explained: (min(N, J),) fraction of the length variance per component.
        coeffs: (N, Kb) coefficients of the input bodies, in standard deviations.
    """

    mean_lengths: torch.Tensor
    directions: torch.Tensor
    std: torch.Tensor
    explained: torch.Tensor
    coeffs: torch.Tensor

    def basis(self, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(b_mean (J,), P_b (Kb, J)): mean and basis divided by ``reference`` lengths (Eq. 5.4)."""
        return self.mean_lengths / reference, self.directions * self.std[:, None] / reference

    def project(self, lengths: torch.Tensor) -> torch.Tensor:
        """(N, J) lengths -> (N, Kb) coefficients in standard deviations."""
        return (lengths - self.mean_lengths) @ self.directions.T / self.std


def bone_pca(lengths: torch.Tensor, num_coeffs: int, mirror: Sequence[int] | None = None) -> BonePCA:
    """PCA of bone lengths (Sec. 5.4.2), each body first averaged with its mirror image.

    Args:
        lengths: (N, J) bone lengths in metres, N >= 2.
        num_coeffs: number of components kept, <= J.
        mirror: (J,) bone mirror index; None skips the symmetrisation.

    Returns:
        :class:`BonePCA`.
    """
    if lengths.dim() != 2 or lengths.shape[0] < 2:
        raise ValueError(f"bone lengths must be (N >= 2, J), got {tuple(lengths.shape)}")
    x = lengths.double()
    if mirror is not None:
        x = 0.5 * (x + x[:, list(mirror)])
    mean = x.mean(0)
    _, sv, vt = torch.linalg.svd(x - mean, full_matrices=False)
    var = sv**2 / (x.shape[0] - 1)
    explained = var / var.sum().clamp(min=1e-30)
    k = min(num_coeffs, vt.shape[0])
    if k < num_coeffs:
        raise ValueError(f"bone PCA needs at least {num_coeffs} bodies for {num_coeffs} components, got {x.shape[0]}")
    # Components with (numerically) zero variance keep a tiny std so the coefficients stay finite.
    std = var[:k].sqrt().clamp(min=1e-9 * float(mean.abs().max()))
    directions = vt[:k]
    if mirror is not None:
        directions = 0.5 * (directions + directions[:, list(mirror)])
        directions = directions / directions.norm(dim=1, keepdim=True).clamp(min=1e-30)
    pca = BonePCA(mean, directions, std, explained, torch.zeros(0))
    pca.coeffs = pca.project(x)
    return pca


def _mirror_vertices(v: torch.Tensor, mirror: torch.Tensor) -> torch.Tensor:
    """(..., V, 3) -> mirror image across x = 0 in the same vertex order."""
    return v[..., mirror, :] * v.new_tensor(_FLIP)


def symmetrize_vertices(v: torch.Tensor, mirror: torch.Tensor) -> torch.Tensor:
    """Average (..., V, 3) positions or offsets with their mirror image (exactly symmetric)."""
    return 0.5 * (v + _mirror_vertices(v, mirror))


def blend_weights(raw: torch.Tensor, mask: torch.Tensor, eps: float) -> torch.Tensor:
    """Eq. 5.31: ``W = f(W') / sum_j f(W')_ij`` with ``f(x) = sqrt(x^2 + eps)``, on a support.

    Args:
        raw: (V, J) free parameters W'.
        mask: (V, J) bool support; at least one True per row.
        eps: epsilon of f.

    Returns:
        (V, J) weights, >= 0, zero off the support, rows summing to 1.
    """
    f = torch.sqrt(raw * raw + eps) * mask
    return f / f.sum(1, keepdim=True)


def weight_support(weights: torch.Tensor, parents: Sequence[int]) -> torch.Tensor:
    """(V, J) bool: each vertex's bones with non-zero weight plus their parents and children."""
    nz = weights > 0
    adj = torch.eye(len(parents), dtype=torch.bool, device=weights.device)
    for j, p in enumerate(parents):
        if p >= 0:
            adj[j, p] = adj[p, j] = True
    return (nz.float() @ adj.float()) > 0


def _blended(weights: torch.Tensor, transforms: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-vertex blended transforms of Eq. 5.12: (B, V, 3, 3) M and (B, V, 3) t."""
    blend = torch.einsum("vj,njab->nvab", weights, transforms)
    return blend[..., :3], blend[..., 3]


def solve_correctives(
    targets: torch.Tensor,
    coeffs: torch.Tensor,
    linear: torch.Tensor,
    offset: torch.Tensor,
    ridge: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact minimiser of Eq. 5.27 for fixed per-vertex blended transforms.

    Minimises ``sum_n sum_i ||M_ni (v_i + sum_k c_nk p_ki) + t_ni - s_ni||^2 + ridge * sum ||p||^2``
    over v (V, 3) and p (Kb, V, 3), vertex by vertex.

    Args:
        targets: (N, V, 3) registrations S^ (posed), metres.
        coeffs: (N, Kb) bone coefficients c_b.
        linear: (N, V, 3, 3) blended linear parts M_ni.
        offset: (N, V, 3) blended translations t_ni.
        ridge: penalty on the correctives (absolute, not per registration).

    Returns:
        (template (V, 3), correctives (Kb, V, 3)) in float64.
    """
    normal, rhs = _normal_equations(targets, coeffs, linear, offset)
    return _solve_normal(normal, rhs, ridge)


def _normal_equations(targets, coeffs, linear, offset):
    f64 = torch.float64
    n, v = targets.shape[:2]
    a = torch.cat([torch.ones(n, 1, dtype=f64, device=coeffs.device), coeffs.to(f64)], 1)  # (N, K1)
    m = linear.to(f64)
    g = m.transpose(-1, -2) @ m  # (N, V, 3, 3)
    r = (m.transpose(-1, -2) @ (targets.to(f64) - offset.to(f64))[..., None])[..., 0]  # (N, V, 3)
    k1 = a.shape[1]
    aa = (a[:, :, None] * a[:, None]).reshape(n, k1 * k1)
    normal = (aa.T @ g.reshape(n, v * 9)).reshape(k1, k1, v, 3, 3)
    rhs = (a.T @ r.reshape(n, v * 3)).reshape(k1, v, 3)
    return normal, rhs


def _solve_normal(normal: torch.Tensor, rhs: torch.Tensor, ridge: float):
    k1, _, v = normal.shape[:3]
    mat = normal.permute(2, 0, 3, 1, 4).reshape(v, 3 * k1, 3 * k1)  # (V, K1*3, K1*3)
    diag = torch.full((3 * k1,), float(ridge), dtype=mat.dtype, device=mat.device)
    diag[:3] = 1e-12  # the mean is always determined (M_ni is invertible)
    mat = mat + torch.diag(diag)
    sol = torch.linalg.solve(mat, rhs.permute(1, 0, 2).reshape(v, 3 * k1, 1))[..., 0]
    sol = sol.reshape(v, k1, 3)
    return sol[:, 0], sol[:, 1:].permute(1, 0, 2).contiguous()


def shape_pca(
    residuals: torch.Tensor, num_coeffs: int, mirror: torch.Tensor, symmetry: str = "symmetrize"
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Shape PCA of T-pose residuals (Eqs. 5.28, 5.8).

    Args:
        residuals: (N, V, 3) V_D in metres.
        num_coeffs: components kept (at most the number of samples - 1).
        mirror: (V,) vertex mirror map.
        symmetry: ``symmetrize`` (average each sample with its mirror) or ``augment`` (add mirrors).

    Returns:
        mean (V, 3), basis (Ks, V, 3) metres per standard deviation, coefficients (N, Ks) of the
        input samples in standard deviations, explained (Ks,) variance fractions.
    """
    n, v = residuals.shape[:2]
    x = residuals.double()
    if symmetry == "symmetrize":
        data = symmetrize_vertices(x, mirror)
    elif symmetry == "augment":
        data = torch.cat([x, _mirror_vertices(x, mirror)])
    else:
        raise ValueError(f"symmetry must be one of {SYMMETRY_MODES}, got {symmetry!r}")
    mean = data.mean(0)
    flat = (data - mean).reshape(len(data), -1)
    k = min(num_coeffs, len(data) - 1)
    if k < 1:
        raise ValueError(f"shape PCA needs at least 2 samples, got {n}")
    total = flat.pow(2).sum() / (len(data) - 1)
    if len(data) <= 4 * (k + 10):
        _, sv, vt = torch.linalg.svd(flat, full_matrices=False)
    else:
        _, sv, vh = torch.svd_lowrank(flat, q=k + 10, niter=4)
        vt = vh.T
    var = sv[:k] ** 2 / (len(data) - 1)
    std = var.sqrt().clamp(min=1e-12)
    directions = vt[:k]  # (Ks, 3V)
    if symmetry == "symmetrize":  # exact symmetry despite round-off
        d3 = directions.reshape(k, v, 3)
        directions = symmetrize_vertices(d3, mirror).reshape(k, -1)
    basis = (directions * std[:, None]).reshape(k, v, 3)
    coeffs = (x - mean).reshape(n, -1) @ directions.T / std
    return mean, basis, coeffs, var / total.clamp(min=1e-30)


# ------------------------------------------------------------------------------------------------
# Fitting (Eq. 5.26) and reconstruction


def _templates(mdl: _Model, st: _State, idx: torch.Tensor | None, base: torch.Tensor | None) -> torch.Tensor:
    """Person templates ``V_mean + c_b P_bc + c_s P_s`` (+ fixed ``base`` offsets) on vertices idx."""
    sel = slice(None) if idx is None else idx
    t = mdl.template[sel].expand(st.bone.shape[0], -1, -1)
    t = t + torch.einsum("bk,kvc->bvc", st.bone, mdl.correctives[:, sel])
    if st.shape is not None and mdl.shape_basis is not None:
        t = t + torch.einsum("bk,kvc->bvc", st.shape, mdl.shape_basis[:, sel])
    if base is not None:
        t = t + base[:, sel]
    return t


def _posed(model, mdl: _Model, st: _State, idx=None, base=None, weights=None, x=None):
    w = mdl.weights if weights is None else weights
    sel = slice(None) if idx is None else idx
    b = mdl.bone_mean + st.bone @ mdl.bone_basis  # Eq. 5.4
    kw = dict(pose=x) if x is not None else dict(angles=st.angles)
    return pose(
        model, _templates(mdl, st, idx, base), bone_scales=b, global_orient=st.global_orient,
        transl=st.transl, weights=w[sel], heads=mdl.heads, **kw,
    )  # fmt: skip


def fit_pose_and_bones(
    model,
    mdl: _Model,
    targets: torch.Tensor,
    init: _State,
    cfg: FitConfig,
    fit_bones: bool = True,
    base: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
) -> _State:
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
            cur = _State(st.angles, cb, go, tr, st.shape)
            pv = _posed(model, mdl, cur, idx, bse, x=x).vertices
            sq = (pv - tgt).pow(2).sum(-1).mean(-1) * 1e6  # (B,) mean squared distance, mm^2
            loss = sq.sum() + cfg.bone_prior * cb.pow(2).sum()
            if not torch.isfinite(loss):
                raise FloatingPointError("non-finite loss while fitting pose and bone coefficients")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        with torch.no_grad():
            theta = pose(model, mdl.template[:1], pose=x).angles
        out.append(_State(theta.detach(), cb.detach(), go.detach(), tr.detach(), st.shape))
    return _State(
        torch.cat([o.angles for o in out]), torch.cat([o.bone for o in out]),
        torch.cat([o.global_orient for o in out]), torch.cat([o.transl for o in out]), init.shape,
    )  # fmt: skip


@torch.no_grad()
def _unskinned(model, mdl: _Model, targets: torch.Tensor, st: _State, batch: int) -> torch.Tensor:
    """T-pose positions of the registrations (inverse of Eq. 5.12 per vertex), (N, V, 3)."""
    out = []
    for s in range(0, targets.shape[0], batch):
        sub = st.take(slice(s, s + batch))
        tr = _posed(model, mdl, sub, idx=torch.arange(1, device=targets.device)).transforms
        out.append(unskin(targets[s : s + batch], mdl.weights, tr))
    return torch.cat(out)


@torch.no_grad()
def _fit_shape(model, mdl: _Model, targets: torch.Tensor, st: _State, batch: int) -> torch.Tensor:
    """Closed-form c_s: least squares of the un-skinned residual on P_s (Eq. 5.28 projected)."""
    resid = _unskinned(model, mdl, targets, st, batch) - _templates(mdl, _State(st.angles, st.bone, st.global_orient, st.transl), None, None)
    basis = mdl.shape_basis.reshape(mdl.shape_basis.shape[0], -1).double()
    gram = basis @ basis.T + 1e-10 * torch.eye(basis.shape[0], dtype=basis.dtype, device=basis.device)
    return torch.linalg.solve(gram, basis @ resid.reshape(len(resid), -1).double().T).T.to(targets.dtype)


@torch.no_grad()
def _errors_mm(model, mdl: _Model, targets: torch.Tensor, st: _State, batch: int, base=None, weights=None) -> torch.Tensor:
    """(N,) mean per-vertex distance in mm between the model reconstruction and the targets."""
    out = []
    for s in range(0, targets.shape[0], batch):
        sl = slice(s, s + batch)
        pv = _posed(model, mdl, st.take(sl), base=None if base is None else base[sl], weights=weights).vertices
        out.append((pv - targets[sl]).norm(dim=-1).mean(-1) * 1000.0)
    return torch.cat(out)


def fit_full(model, mdl: _Model, targets: torch.Tensor, init: _State, cfg: FitConfig, generator=None) -> _State:
    """Fit theta, c_b and (if the model has a shape basis) c_s, alternating Adam and closed form."""
    st = init
    if mdl.shape_basis is not None and st.shape is None:
        st = dataclasses.replace(st, shape=torch.zeros(len(targets), mdl.shape_basis.shape[0], device=targets.device))
    rounds = cfg.shape_rounds if mdl.shape_basis is not None else 1
    for _ in range(rounds):
        st = fit_pose_and_bones(model, mdl, targets, st, cfg, generator=generator)
        if mdl.shape_basis is not None:
            st = dataclasses.replace(st, shape=_fit_shape(model, mdl, targets, st, cfg.batch_size))
    return st


# ------------------------------------------------------------------------------------------------
# The pipeline


def _stack(regs: Sequence[Any], device: torch.device) -> tuple[torch.Tensor, _State, torch.Tensor]:
    f32 = torch.float32

    def t(name: str) -> torch.Tensor:
        return torch.as_tensor(np.stack([np.asarray(getattr(r, name), dtype=np.float32) for r in regs]), dtype=f32, device=device)

    st = _State(t("angles"), torch.zeros(0), t("global_orient"), t("transl"))
    return t("vertices"), st, t("bone_scales")


def _check_registrations(regs: Sequence[Any], model) -> None:
    v, j, d = model.num_vertices, model.num_joints, model.num_dofs
    for i, r in enumerate(regs):
        for name, shape in (("vertices", (v, 3)), ("bone_scales", (j,)), ("angles", (d,)), ("global_orient", (3,)), ("transl", (3,))):
            if not hasattr(r, name):
                raise ValueError(f"registration {i}: missing attribute {name!r}")
            a = np.asarray(getattr(r, name))
            if a.shape != shape:
                raise ValueError(f"registration {i}: {name} must be {shape}, got {a.shape}")
            if not np.isfinite(a).all():
                raise ValueError(f"registration {i}: {name} has non-finite values")
        if not isinstance(getattr(r, "meta", None), dict):
            raise ValueError(f"registration {i}: meta must be a dict")


def _subject(meta: dict[str, Any], i: int) -> str:
    return str(meta.get("subject", f"#{i}"))


def learn_model(initial_model, registrations: Sequence[Any], config: TrainConfig | None = None) -> tuple[io.ModelData, dict]:
    """Learn b_mean, P_b, V_mean, P_bc, P_s and W from registrations (Eqs. 5.26-5.31).

    Args:
        initial_model: a :class:`blsm.BLSM` (the packaged one): template, skeleton, weights.
        registrations: objects with ``vertices`` (V, 3), ``bone_scales`` (J,), ``angles`` (47,),
            ``global_orient`` (3,), ``transl`` (3,) (numpy or torch) and ``meta`` (dict; see
            :func:`is_rest_pose`; ``split`` "test" registrations are only evaluated).
        config: :class:`TrainConfig` (defaults if None).

    Returns:
        (model data accepted by :func:`blsm.io.save_model`, report dict: explained variances,
        reconstruction errors in mm after each step, timings in seconds).
    """
    cfg = config or TrainConfig()
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    device = torch.device(cfg.device)
    model = initial_model.float().to(device)
    _check_registrations(registrations, model)
    metas = [dict(r.meta) for r in registrations]
    train = [i for i, m in enumerate(metas) if _split(m) == "train"]
    test = [i for i, m in enumerate(metas) if _split(m) == "test"]
    rest = [i for i in train if is_rest_pose(metas[i])]
    posed = [i for i in train if not is_rest_pose(metas[i])]
    kb, ks = cfg.bone.num_coeffs, cfg.shape.num_coeffs
    if len(rest) < max(kb, 2) + 1:
        raise ValueError(f"need more than {max(kb, 2)} rest-pose training registrations for {kb} bone coefficients, got {len(rest)}")
    report: dict[str, Any] = {"registrations": {"train_rest": len(rest), "train_posed": len(posed), "test": len(test)}, "seconds": {}, "errors_mm": {}}
    timer = time.perf_counter()
    t_all = timer

    def lap(name: str) -> None:
        nonlocal timer
        now = time.perf_counter()
        report["seconds"][name] = round(now - timer, 2)
        timer = now

    targets_all, st_all, scales_all = _stack(registrations, device)
    mirror = model.vertex_mirror
    bmir = bone_mirror_index(model.bone_names)
    bs = cfg.fit.batch_size
    _log(f"{len(rest)} rest-pose and {len(posed)} posed training registrations, {len(test)} test")

    # 1. Bone basis (Sec. 5.4.2).
    lengths0 = template_bone_lengths(model)  # (J,) of the initial skeleton
    ridx = torch.as_tensor(rest, device=device)
    lengths = scales_all[ridx].double() * lengths0.double()
    pca = bone_pca(lengths, kb, bmir)
    mean_scale_old = (pca.mean_lengths / lengths0.double()).float()  # b_mean on the initial skeleton
    if cfg.bone.rebase_skeleton:
        ref = pca.mean_lengths
        with torch.no_grad():
            rb = pose(model, model.template, bone_scales=mean_scale_old[None])
        par = model.parents_t.clamp(min=0)
        scaled = mean_scale_old[par, None] * (model.heads - model.heads[par])
        heads = model.heads[0] + model.chain @ scaled  # joints of the rebased bind skeleton
        template = symmetrize_vertices(rb.vertices[0], mirror)
    else:
        ref = lengths0.double()
        heads, template = model.heads.clone(), model.template.clone()
    b_mean, p_b = (t.float() for t in pca.basis(ref))
    p_b = 0.5 * (p_b + p_b[:, bmir])
    report["bone_pca_explained"] = [float(x) for x in pca.explained[:kb]]
    report["bone_pca_explained_first3"] = float(pca.explained[:3].sum())
    _log(f"bone PCA: first 3 components explain {100 * report['bone_pca_explained_first3']:.2f} % of bone-length variance")
    mdl = _Model(heads.float(), template.float(), model.weights.clone(), b_mean, p_b, torch.zeros(kb, model.num_vertices, 3, device=device))

    # Initial c_b of every registration: stage-1 lengths projected on the basis.
    st_all.bone = pca.project(scales_all.double() * lengths0.double()).float()
    lap("bone_basis")

    # 2 + 3. Alternate Eq. 5.26 (fit) and Eq. 5.27 (solve) on the rest-pose training registrations.
    tgt_rest = targets_all[ridx]
    st_rest = st_all.take(ridx)
    for a in range(cfg.correctives.alternations):
        st_rest = fit_pose_and_bones(model, mdl, tgt_rest, st_rest, cfg.fit, generator=gen)
        err = float(_errors_mm(model, mdl, tgt_rest, st_rest, bs).mean())
        report["errors_mm"][f"fit_{a}"] = err
        lap(f"fit_{a}")
        _log(f"alternation {a}: Eq. 5.26 fit, training error {err:.2f} mm ({report['seconds'][f'fit_{a}']:.1f} s)")
        normal = rhs = None
        with torch.no_grad():
            for s in range(0, len(rest), bs):
                sub = st_rest.take(slice(s, s + bs))
                tr = _posed(model, mdl, sub, idx=torch.arange(1, device=device)).transforms
                m, t = _blended(mdl.weights, tr)
                nrm, r = _normal_equations(tgt_rest[s : s + bs], sub.bone, m, t)
                normal = nrm if normal is None else normal + nrm
                rhs = r if rhs is None else rhs + r
            vbar, pbc = _solve_normal(normal, rhs, cfg.correctives.ridge * len(rest))
        mdl.template = symmetrize_vertices(vbar, mirror).float()
        mdl.correctives = symmetrize_vertices(pbc, mirror).float()
        err = float(_errors_mm(model, mdl, tgt_rest, st_rest, bs).mean())
        report["errors_mm"][f"correctives_{a}"] = err
        lap(f"correctives_{a}")
        _log(f"alternation {a}: Eq. 5.27 solve, training error {err:.2f} mm ({report['seconds'][f'correctives_{a}']:.1f} s)")

    # 4. Shape PCA of the T-pose residuals (Eqs. 5.28, 5.8).
    unposed = _unskinned(model, mdl, tgt_rest, st_rest, bs)
    resid = unposed - _templates(mdl, dataclasses.replace(st_rest, shape=None), None, None)
    smean, sbasis, c_s, sexpl = shape_pca(resid, ks, mirror, cfg.shape.symmetry)
    mdl.template = symmetrize_vertices(mdl.template + smean.float(), mirror)
    mdl.shape_basis = sbasis.float()
    st_rest = dataclasses.replace(st_rest, shape=c_s.float())
    if sbasis.shape[0] < ks:
        _log(f"shape PCA: only {sbasis.shape[0]} components (fewer samples than {ks}); padding with zeros")
        pad = torch.zeros(ks - sbasis.shape[0], *sbasis.shape[1:], device=device)
        mdl.shape_basis = torch.cat([mdl.shape_basis, pad])
        st_rest.shape = torch.cat([st_rest.shape, torch.zeros(len(rest), ks - sbasis.shape[0], device=device)], 1)
        sexpl = torch.cat([sexpl, sexpl.new_zeros(ks - len(sexpl))])
    report["shape_pca_explained"] = [float(x) for x in sexpl]
    err = float(_errors_mm(model, mdl, tgt_rest, st_rest, bs).mean())
    report["errors_mm"]["shape"] = err
    lap("shape_basis")
    _log(f"shape PCA ({ks} components, {100 * float(sexpl.sum()):.1f} % of residual variance): training error {err:.2f} mm")

    # 5. Blend weights (Eqs. 5.30, 5.31) from the posed training registrations.
    if cfg.weights.enabled and posed:
        mdl.weights = _learn_weights(model, mdl, metas, rest, posed, st_rest, unposed, targets_all, st_all, cfg, report, gen)
        lap("weights")
    else:
        report["weights"] = {"skipped": True}

    # Population coefficients; held-out evaluation.
    if test:
        tidx = torch.as_tensor(test, device=device)
        st_test = fit_full(model, mdl, targets_all[tidx], st_all.take(tidx), cfg.fit, generator=gen)
        terr = _errors_mm(model, mdl, targets_all[tidx], st_test, bs)
        report["errors_mm"]["test"] = float(terr.mean())
        lap("test")
        _log(f"held-out ({len(test)} registrations): {float(terr.mean()):.2f} mm")
    report["seconds"]["total"] = round(time.perf_counter() - t_all, 2)
    data = _assemble(initial_model, mdl, st_rest, report, cfg)
    return data, report


def _learn_weights(model, mdl, metas, rest, posed, st_rest, unposed, targets_all, st_all, cfg, report, gen) -> torch.Tensor:
    device = mdl.template.device
    wc, bs = cfg.weights, cfg.fit.batch_size
    # Per-subject T-pose templates and bone coefficients from the rest-pose registrations.
    subj_rest: dict[str, int] = {}
    for k, i in enumerate(rest):
        subj_rest.setdefault(_subject(metas[i], i), k)
    pidx = torch.as_tensor(posed, device=device)
    tgt = targets_all[pidx]
    st = st_all.take(pidx)
    n = len(posed)
    base = torch.zeros(n, *mdl.template.shape, device=device)  # V^_D of the subject
    bone = st.bone.clone()
    shape = torch.zeros(n, mdl.shape_basis.shape[0], device=device)
    have = torch.zeros(n, dtype=torch.bool)
    for k, i in enumerate(posed):
        r = subj_rest.get(_subject(metas[i], i))
        if r is not None:
            sub = st_rest.take(slice(r, r + 1))
            bone[k], shape[k] = sub.bone[0], sub.shape[0]
            # V^_D: the subject's un-skinned rest registration minus its model template, so that
            # V_mean + V_b + V_s + V^_D is that un-skinned registration.
            base[k] = unposed[r] - _templates(mdl, sub, None, None)[0]
            have[k] = True
    st = _State(st.angles, bone, st.global_orient, st.transl, shape)
    if (~have).any():
        miss = torch.nonzero(~have)[:, 0].to(device)
        fitted = fit_full(model, mdl, tgt[miss], st.take(miss), cfg.fit, generator=gen)
        st.bone[miss], st.shape[miss] = fitted.bone, fitted.shape
        st.angles[miss], st.global_orient[miss], st.transl[miss] = fitted.angles, fitted.global_orient, fitted.transl
    _log(f"weights: {int(have.sum())} posed registrations use their subject's rest-pose template, {int((~have).sum())} the fitted model")
    w0 = mdl.weights
    mask = weight_support(w0, model.parents)
    vm, bm = model.vertex_mirror, bone_mirror_index(model.bone_names)
    raw = w0.clone().requires_grad_(True)
    opt = torch.optim.Adam([raw], lr=wc.lr)
    w, err0 = w0, None
    t0 = time.perf_counter()
    for rnd in range(wc.rounds):
        cur = dataclasses.replace(mdl, weights=w.detach())
        st = fit_pose_and_bones(model, cur, tgt, st, cfg.fit, base=base, generator=gen)
        if err0 is None:
            err0 = _errors_mm(model, cur, tgt, st, bs, base=base)
            report["errors_mm"]["posed_before_weights"] = float(err0.mean())
        with torch.no_grad():  # fixed per-registration transforms: theta, c_b do not change here
            trs, tmpls = [], []
            for s in range(0, n, bs):
                sub = st.take(slice(s, s + bs))
                trs.append(_posed(model, cur, sub, idx=torch.arange(1, device=device)).transforms)
                tmpls.append(_templates(cur, sub, None, base[s : s + bs]))
            trs, tmpls = torch.cat(trs), torch.cat(tmpls)
        for it in range(wc.iterations):
            batch = torch.randperm(n, generator=gen)[: wc.batch_size].to(device)
            w = blend_weights(0.5 * (raw + raw[vm][:, bm]), mask, wc.eps)  # Eq. 5.31, symmetric
            tr = trs[batch]
            pv = linear_blend_skinning(tmpls[batch], w, tr[..., :3], tr[..., 3])
            loss = (pv - tgt[batch]).pow(2).sum(-1).mean() * 1e6 + wc.regularizer * (w - w0).pow(2).sum(-1).mean()
            if not torch.isfinite(loss):
                raise FloatingPointError("non-finite loss while learning blend weights")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        with torch.no_grad():
            w = blend_weights(0.5 * (raw + raw[vm][:, bm]), mask, wc.eps)
        _log(f"weights: round {rnd}, posed training error {float(_errors_mm(model, cur, tgt, st, bs, base=base, weights=w).mean()):.2f} mm")
    with torch.no_grad():
        if wc.prune_below > 0:
            w = torch.where(w < wc.prune_below, torch.zeros_like(w), w)
            w = w / w.sum(1, keepdim=True)
    st = fit_pose_and_bones(model, dataclasses.replace(mdl, weights=w), tgt, st, cfg.fit, base=base, generator=gen)
    err1 = _errors_mm(model, mdl, tgt, st, bs, base=base, weights=w)
    report["errors_mm"]["posed_after_weights"] = float(err1.mean())
    report["weights"] = {"support_per_vertex": float(mask.sum(1).float().mean()), "max_change": float((w - w0).abs().max()), "seconds": round(time.perf_counter() - t0, 2)}
    _log(f"weights: posed training error {float(err0.mean()):.2f} -> {float(err1.mean()):.2f} mm")
    return w.detach()


def _assemble(initial_model, mdl: _Model, st_rest: _State, report: dict, cfg: TrainConfig) -> io.ModelData:
    """A ModelData with every array of the initial model; the learned ones replaced."""
    src = initial_model
    if getattr(src, "meta", None) is None:
        raise ValueError("initial_model must be a blsm.BLSM")

    def np32(t: torch.Tensor) -> np.ndarray:
        return t.detach().cpu().numpy().astype(np.float32)

    def npi(t: torch.Tensor) -> np.ndarray:
        return t.detach().cpu().numpy().astype(np.int32)

    weights = mdl.weights.detach().cpu().double()
    weights = (weights / weights.sum(1, keepdim=True)).numpy().astype(np.float32)
    arrays = {
        "template": np32(mdl.template),
        "faces": npi(src.faces),
        "uvs": np32(src.uvs),
        "faces_uv": npi(src.faces_uv),
        "weights": weights,
        "heads": mdl.heads.detach().cpu().numpy().astype(np.float64),
        "frames": src.frames.detach().cpu().numpy().astype(np.float64),
        "bone_mean": np32(mdl.bone_mean),
        "bone_basis": np32(mdl.bone_basis),
        "bone_correctives": np32(mdl.correctives),
        "shape_basis": np32(mdl.shape_basis),
        "population_bone": np32(st_rest.bone),
        "population_shape": np32(st_rest.shape),
        "vertex_parts": npi(src.vertex_parts),
        "vertex_bones": weights.argmax(1).astype(np.int32),
        "vertex_mirror": npi(src.vertex_mirror),
        "keypoint_joint": npi(src.keypoint_joint),
        "keypoint_vertices": npi(src.keypoint_vertices),
        "keypoint_weights": np32(src.keypoint_weights),
    }
    meta = dict(src.meta)
    meta.pop("build_report", None)
    meta["name"] = "blsm-learned"
    meta["built"] = datetime.date.today().isoformat()
    meta["train_report"] = report
    meta["train_config"] = dataclasses.asdict(cfg)
    return io.ModelData(arrays=arrays, meta=meta, dof_table_yaml=src.dof_table.source)


def load_registrations(paths: Sequence[str | Path]) -> list[Any]:
    """Read registration files (``blsm-registration`` v1, :mod:`blsm.learn.register`); folders
    are expanded to their ``*.npz`` files in sorted order."""
    from blsm.learn.register import load_registration  # helper module, written alongside

    files: list[Path] = []
    for p in map(Path, paths):
        files.extend(sorted(p.glob("*.npz")) if p.is_dir() else [p])
    if not files:
        raise ValueError(f"no registration files in {', '.join(map(str, paths))}")
    return [load_registration(f) for f in files]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="blsm learn", description=__doc__.splitlines()[0])
    parser.add_argument("registrations", nargs="+", type=Path, help="registration files or folders")
    parser.add_argument("--config", type=Path, default=None, help="YAML run config (its train: section)")
    parser.add_argument("--model", type=Path, default=None, help="initial model (default: the packaged one)")
    parser.add_argument("--out", type=Path, required=True, help="learned model file (.npz)")
    parser.add_argument("--report", type=Path, default=None, help="JSON report (default: <out>.report.json)")
    args = parser.parse_args(argv)
    from blsm.model import load

    try:
        cfg = load_train_config(args.config) if args.config is not None else TrainConfig()
        regs = load_registrations(args.registrations)
        data, report = learn_model(load(args.model), regs, cfg)
    except ValueError as exc:
        parser.exit(2, f"{parser.prog}: error: {exc}\n")
    io.save_model(data, args.out)
    report_path = args.report or args.out.with_suffix(".report.json")
    with io.atomic_write(report_path, "w") as fh:
        json.dump(report, fh, indent=1)
    _log(f"wrote {args.out} and {report_path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
