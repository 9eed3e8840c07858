"""Staged fitting of a body model to registrations (thesis Sec. 5.5.2).

The models compared in Sec. 5.5 are aligned to registered meshes S^ (in the template's topology) by
minimising the L2 distance between corresponding vertices with Adam (learning rate 0.1, x0.9 on
plateau), in four stages as in [66]:

1. torso vertices (dominant blend weight on a torso bone); shape coefficients, torso joint angles,
   global orientation and translation;
2. + upper-limb vertices and upper-limb angles;
3. + lower-limb vertices and lower-limb angles;
4. all vertices (head and neck included) and all parameters.

The fitter is generic over models through :class:`Fittable`: a model names its coefficient groups
(BLSM-linear: ``bone`` c_b of Eq. 5.4 and ``shape`` c_s of Eq. 5.8; SMPL-reimpl: ``shape``) and maps
a parameter dict to vertices. Pose is always the 47 unconstrained atoms of Eq. 5.6, so every fitted
pose respects the joint limits.

Units: metres and radians; errors are Euclidean per-vertex distances in metres.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field

import torch

from blsm.joint_limits import unconstrained_from_angles
from blsm.skeleton import BONE_NAMES, BONE_PARTS, PART_NAMES

# Stage of each six-part label: the thesis' torso -> upper limbs -> lower limbs -> everything.
PART_STAGE: dict[str, int] = {
    "torso": 1,
    "left_arm": 2,
    "right_arm": 2,
    "left_leg": 3,
    "right_leg": 3,
    "head": 4,
}
NUM_STAGES = 4
MM2 = 1e6  # losses in mm^2: keeps L-BFGS tolerances meaningful in float32


class Fittable(abc.ABC):
    """What :func:`staged_fit` needs from a model (a small protocol with shared helpers).

    Subclasses set ``skeleton`` (a :class:`blsm.BLSM` giving bones, DoF table and blend weights),
    ``coeff_sizes`` (ordered dict: group name -> number of coefficients) and implement
    :meth:`vertices`.
    """

    skeleton: torch.nn.Module
    coeff_sizes: dict[str, int]

    @abc.abstractmethod
    def vertices(self, params: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B, V, 3) posed vertices in metres of ``params`` (see :func:`staged_fit`)."""

    @property
    def num_coeffs_max(self) -> int:
        return sum(self.coeff_sizes.values())

    def free_coeffs(self, num_coeffs: int) -> dict[str, int]:
        """How many coefficients of each group are free for ``num_coeffs`` in total.

        Groups are filled in order (BLSM-linear: the first min(k, Kb) bone coefficients, then
        k - Kb shape coefficients, as Fig. 5.6 counts bone and shape blendshapes together).
        """
        if num_coeffs < 0 or num_coeffs > self.num_coeffs_max:
            raise ValueError(f"num_coeffs must be in [0, {self.num_coeffs_max}], got {num_coeffs}")
        out, left = {}, num_coeffs
        for name, size in self.coeff_sizes.items():
            out[name] = min(left, size)
            left -= out[name]
        return out

    def vertex_stage(self) -> torch.Tensor:
        """(V,) long: the stage (1-4) from which each vertex enters the loss."""
        bone_stage = torch.tensor([PART_STAGE[PART_NAMES[p]] for p in BONE_PARTS])
        names = list(self.skeleton.bone_names)
        if names != list(BONE_NAMES):
            raise ValueError(f"model bones {names} differ from blsm.skeleton.BONE_NAMES")
        return bone_stage[self.skeleton.vertex_bones.cpu()]

    def dof_stage(self) -> torch.Tensor:
        """(47,) long: the stage (1-4) from which each pose atom is optimised."""
        names = list(self.skeleton.bone_names)
        part = [BONE_PARTS[names.index(d.joint)] for d in self.skeleton.dof_table.dofs]
        return torch.tensor([PART_STAGE[PART_NAMES[p]] for p in part])


class BLSMFittable(Fittable):
    """BLSM-linear: ``vertices = BLSM(pose, c_b, c_s, R, t)`` (Eqs. 5.1-5.12).

    Also BLSM-spiral (paper 000 Eq. 11): a model whose ``shape_decoder`` is a
    :class:`blsm.spiral.shape.SpiralShapeDecoder` takes its latent code z as ``shape``, so the group
    ``shape`` holds z (L entries) and ``num_coeffs = Kb + L`` frees every bone and latent coefficient.
    The staged fit and its Levenberg-Marquardt polish differentiate through the decoder.
    """

    def __init__(self, model: torch.nn.Module) -> None:
        self.skeleton = model
        self.model = model
        self.coeff_sizes = {"bone": model.num_bone_coeffs, "shape": model.num_shape_coeffs}

    def vertices(self, params: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.model(
            pose=params["pose"],
            bone=params["bone"],
            shape=params["shape"],
            global_orient=params["global_orient"],
            transl=params["transl"],
        ).vertices


@dataclass
class FitConfig:
    """Settings of :func:`staged_fit` (Sec. 5.5.2).

    Attributes:
        iterations: Adam steps per stage (4 entries).
        lr: Adam learning rate (thesis: 0.1).
        plateau_factor: learning-rate factor on a plateau (thesis: 0.9).
        plateau_patience: steps without a 1e-4 relative improvement that count as a plateau.
        coeff_l2: weight of a small ``sum c^2`` prior on the coefficients (0 = pure L2 data term).
        lm_iterations: Levenberg-Marquardt steps polishing stage 4 after Adam (not in the
            thesis; 0 = off). Adam at lr 0.1 creeps along the narrow valleys where spine / hip
            atoms, global orientation and coefficients trade off and stops a few mm short
            (1-6 mm on exactly representable BLSM bodies); about 25 damped Gauss-Newton steps
            from there reach the least-squares optimum. Stops early once no body improves.
    """

    iterations: tuple[int, int, int, int] = (100, 100, 100, 200)
    lr: float = 0.1
    plateau_factor: float = 0.9
    plateau_patience: int = 10
    coeff_l2: float = 0.0
    lm_iterations: int = 0

    def __post_init__(self) -> None:
        if len(self.iterations) != NUM_STAGES or any(int(i) < 0 for i in self.iterations):
            raise ValueError(f"iterations must be 4 non-negative ints, got {self.iterations}")
        if self.lr <= 0 or not 0 < self.plateau_factor <= 1:
            raise ValueError(f"need lr > 0 and 0 < plateau_factor <= 1, got {self.lr}, {self.plateau_factor}")


@dataclass
class FitResult:
    """Result of :func:`staged_fit`.

    Attributes:
        params: fitted parameters: ``pose`` (B, 47) unconstrained (Eq. 5.6), ``angles`` (B, 47)
            radians, ``global_orient`` (B, 3) axis-angle, ``transl`` (B, 3) metres and one (B, K_g)
            tensor per coefficient group (full width; coefficients that were not free are 0 or
            the fixed values given).
        vertices: (B, V, 3) fitted vertices, metres.
        errors: (B, V) per-vertex Euclidean error, metres.
        history: final loss (mean squared vertex distance, mm^2) of each stage that ran.
    """

    params: dict[str, torch.Tensor]
    vertices: torch.Tensor
    errors: torch.Tensor
    history: list[float] = field(default_factory=list)

    @property
    def mean_error(self) -> torch.Tensor:
        """(B,) mean absolute vertex error (MABS) of each registration, metres."""
        return self.errors.mean(1)


def kabsch(source: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rigid alignment ``target ~ R source + t`` of corresponding points (least squares).

    Args:
        source: (B, N, 3) points.
        target: (B, N, 3) points.

    Returns:
        R (B, 3, 3) proper rotations and t (B, 3).
    """
    cs, ct = source.mean(1, keepdim=True), target.mean(1, keepdim=True)
    h = (source - cs).transpose(1, 2) @ (target - ct)  # (B, 3, 3)
    u, _, vt = torch.linalg.svd(h)
    d = torch.sign(torch.linalg.det(vt.transpose(1, 2) @ u.transpose(1, 2)))
    diag = torch.ones_like(cs[:, 0]).clone()  # (B, 3)
    diag[:, 2] = d
    r = vt.transpose(1, 2) @ torch.diag_embed(diag) @ u.transpose(1, 2)
    t = ct[:, 0] - (r @ cs[:, 0, :, None])[..., 0]
    return r, t


def initial_params(
    fittable: Fittable,
    targets: torch.Tensor,
    fixed_coeffs: dict[str, torch.Tensor] | None = None,
) -> dict[str, torch.Tensor]:
    """Rest pose (all angles 0), zero coefficients, and a rigid (Kabsch) alignment of the torso.

    The global rotation about the root joint and the translation are solved in closed form from the
    torso vertices of the model at rest, so stage 1 starts upright and in place.
    """
    from kornia.geometry.conversions import rotation_matrix_to_axis_angle

    batch = targets.shape[0]
    dtype, device = targets.dtype, targets.device
    limits = fittable.skeleton.dof_limits.to(dtype)
    zero = torch.zeros(1, limits.shape[0], dtype=dtype, device=device)
    inside = (limits[:, 0] <= 0) & (limits[:, 1] >= 0)
    rest = torch.where(inside, zero, 0.5 * (limits[:, 0] + limits[:, 1]))
    params: dict[str, torch.Tensor] = {
        "pose": unconstrained_from_angles(rest, limits).expand(batch, -1).clone(),
        "global_orient": torch.zeros(batch, 3, dtype=dtype, device=device),
        "transl": torch.zeros(batch, 3, dtype=dtype, device=device),
    }
    for name, size in fittable.coeff_sizes.items():
        if fixed_coeffs is not None and name in fixed_coeffs:
            params[name] = fixed_coeffs[name].to(dtype).clone()
        else:
            params[name] = torch.zeros(batch, size, dtype=dtype, device=device)
    with torch.no_grad():
        rest_v = fittable.vertices(params)
    torso = fittable.vertex_stage().to(device) == 1
    r, t = kabsch(rest_v[:, torso], targets[:, torso])
    # The model rotates about its root joint h0: R (v - h0) + h0 + transl = R v + t.
    h0 = fittable.skeleton.heads[0].to(dtype)
    params["global_orient"] = rotation_matrix_to_axis_angle(r)
    params["transl"] = t - h0 + (r @ h0)
    return params


def staged_fit(
    fittable: Fittable,
    targets: torch.Tensor,
    num_coeffs: int | None = None,
    config: FitConfig | None = None,
    fixed_coeffs: dict[str, torch.Tensor] | None = None,
    init: dict[str, torch.Tensor] | None = None,
    stages: tuple[int, ...] = (1, 2, 3, 4),
) -> FitResult:
    """Fit ``fittable`` to registrations in the thesis' four stages (Sec. 5.5.2).

    Each stage minimises ``sum_b mean_{i in stage vertices} ||v_bi - s_bi||^2`` (in mm^2) (plus an optional
    ``coeff_l2 * sum c^2``) with a fresh Adam (lr 0.1) and ``ReduceLROnPlateau(factor=0.9)``;
    parameters outside the stage get no gradient, so they keep their values.

    Args:
        fittable: the model (:class:`BLSMFittable`, :class:`blsm.learn.evaluation.smpl_reimpl.SMPLReimplFittable`).
        targets: (B, V, 3) registrations in the model's topology, metres, world frame.
        num_coeffs: total free coefficients k (groups filled in order, see
            :meth:`Fittable.free_coeffs`); None means all of them.
        config: :class:`FitConfig`.
        fixed_coeffs: coefficient groups held fixed at the given (B, K_g) values, e.g. a shape
            fitted on another frame (pose generalisation, Fig. 5.7 right). With every group fixed
            only pose, global orientation and translation are fitted.
        init: starting parameters (as in :attr:`FitResult.params`); default :func:`initial_params`.
        stages: which stages to run, in order (e.g. ``(1,)`` to inspect stage 1 alone).

    Returns:
        :class:`FitResult`.
    """
    cfg = config or FitConfig()
    if targets.dim() != 3 or targets.shape[2] != 3:
        raise ValueError(f"targets must be (B, V, 3), got {tuple(targets.shape)}")
    num_v = int(fittable.skeleton.weights.shape[0])
    if targets.shape[1] != num_v:
        raise ValueError(f"targets have {targets.shape[1]} vertices, the model has {num_v}")
    if not torch.isfinite(targets).all():
        raise ValueError("targets contain NaN or inf")
    if any(s not in range(1, NUM_STAGES + 1) for s in stages):
        raise ValueError(f"stages must be in 1..{NUM_STAGES}, got {stages}")
    batch = targets.shape[0]
    fixed = dict(fixed_coeffs or {})
    for name, value in fixed.items():
        if name not in fittable.coeff_sizes:
            raise ValueError(
                f"unknown coefficient group {name!r}; the model has {list(fittable.coeff_sizes)}"
            )
        if tuple(value.shape) != (batch, fittable.coeff_sizes[name]):
            raise ValueError(
                f"fixed {name} must be ({batch}, {fittable.coeff_sizes[name]}), got {tuple(value.shape)}"
            )
    free = fittable.free_coeffs(fittable.num_coeffs_max if num_coeffs is None else num_coeffs)
    free = {k: (0 if k in fixed else n) for k, n in free.items()}

    if init is None:
        params = initial_params(fittable, targets, fixed)
    else:
        params = {k: v.clone() for k, v in init.items()}
    params.pop("angles", None)
    for name, value in fixed.items():
        params[name] = value.to(targets.dtype).clone()
    dtype, device = targets.dtype, targets.device
    for v in params.values():
        v.requires_grad_(True)

    v_stage = fittable.vertex_stage().to(device)
    d_stage = fittable.dof_stage().to(device)
    coeff_mask = {
        k: (torch.arange(n_all, device=device) < free[k]).to(dtype)
        for k, n_all in fittable.coeff_sizes.items()
    }
    history: list[float] = []
    masks: dict[str, torch.Tensor] = {}
    for stage in stages:
        iters = int(cfg.iterations[stage - 1])
        if iters == 0:
            continue
        vmask = v_stage <= stage
        masks = {
            "pose": (d_stage <= stage).to(dtype),
            "global_orient": torch.ones(3, dtype=dtype, device=device),
            "transl": torch.ones(3, dtype=dtype, device=device),
            **coeff_mask,
        }
        trainable = [params[k] for k in masks if masks[k].any()]
        opt = torch.optim.Adam(trainable, lr=cfg.lr)
        sched = torch.optim.lr_scheduler.ReduceLROnPlateau(
            opt, factor=cfg.plateau_factor, patience=cfg.plateau_patience, threshold=1e-4
        )
        target_s = targets[:, vmask]
        for _ in range(iters):
            opt.zero_grad(set_to_none=False)
            verts = fittable.vertices(params)[:, vmask]
            loss = MM2 * ((verts - target_s) ** 2).sum(-1).mean(-1).sum()
            if cfg.coeff_l2 > 0:
                loss = loss + cfg.coeff_l2 * sum((params[k] ** 2).sum() for k in coeff_mask)
            if not torch.isfinite(loss):
                raise FloatingPointError(f"staged fit: non-finite loss in stage {stage}")
            loss.backward()
            for k, m in masks.items():
                if params[k].grad is not None:
                    params[k].grad.mul_(m)  # parameters outside the stage stay where they are
            opt.step()
            sched.step(float(loss.detach()))
        history.append(float(loss.detach()) / batch)
    if cfg.lm_iterations > 0 and NUM_STAGES in stages:
        masks = {
            "pose": torch.ones(d_stage.shape[0], dtype=dtype, device=device),
            "global_orient": torch.ones(3, dtype=dtype, device=device),
            "transl": torch.ones(3, dtype=dtype, device=device),
            **coeff_mask,
        }
        history.append(_levenberg_marquardt(fittable, params, targets, masks, cfg) / batch)

    out = {k: v.detach() for k, v in params.items()}
    with torch.no_grad():
        verts = fittable.vertices(out)
        out["angles"] = _angles(fittable, out["pose"])
    errors = (verts - targets).norm(dim=-1)
    return FitResult(out, verts, errors, history)


def _levenberg_marquardt(
    fittable: Fittable,
    params: dict[str, torch.Tensor],
    targets: torch.Tensor,
    masks: dict[str, torch.Tensor],
    cfg: FitConfig,
) -> float:
    """Levenberg-Marquardt on the free entries of ``params`` (in place); returns the final loss.

    Each body is an independent least-squares problem with residuals ``v - s`` (3V, in mm); its
    Jacobian (3V, P) is built with forward-mode AD (one ``jvp`` per free parameter, all bodies
    at once, vectorised with ``vmap``), then ``(J^T J + lam diag(J^T J)) d = -J^T r`` per body.
    """
    from torch.func import jvp, vmap

    keys = [k for k in masks if masks[k].any()]
    idx = {k: masks[k].nonzero().squeeze(1) for k in keys}
    sizes = [int(idx[k].numel()) for k in keys]
    batch = targets.shape[0]
    base = {k: v.detach().clone() for k, v in params.items()}

    def unpack(z: torch.Tensor) -> dict[str, torch.Tensor]:
        out = dict(base)
        for k, part in zip(keys, z.split(sizes, dim=1)):
            out[k] = base[k].index_copy(1, idx[k], part)
        return out

    def residual(z: torch.Tensor) -> torch.Tensor:
        return 1e3 * (fittable.vertices(unpack(z)) - targets).reshape(batch, -1)  # (B, 3V) mm

    z = torch.cat([base[k][:, idx[k]] for k in keys], dim=1)  # (B, P)
    num_p = z.shape[1]
    lam = torch.full((batch,), 1e-3, dtype=torch.float64, device=z.device)
    with torch.no_grad():
        r = residual(z)
        cost = (r**2).sum(1)
    for _ in range(cfg.lm_iterations):
        previous = cost.clone()
        tangents = torch.eye(num_p, dtype=z.dtype, device=z.device)[:, None].expand(-1, batch, -1)
        cols = vmap(lambda t: jvp(residual, (z,), (t,))[1], chunk_size=16)(tangents)  # (P, B, 3V)
        jac = cols.permute(1, 2, 0).double()  # (B, 3V, P); normal equations in float64
        jtj = jac.transpose(1, 2) @ jac  # (B, P, P)
        jtr = (jac.transpose(1, 2) @ r.double()[..., None])[..., 0]  # (B, P)
        diag = torch.diagonal(jtj, dim1=1, dim2=2).clamp(min=1e-9)
        for _ in range(8):  # raise the damping of the bodies whose step does not lower the cost
            step = torch.linalg.solve(
                jtj + torch.diag_embed(lam[:, None] * diag), -jtr[..., None]
            )[..., 0].to(z.dtype)
            with torch.no_grad():
                r_new = residual(z + step)
                cost_new = (r_new**2).sum(1)
            better = cost_new < cost
            z = torch.where(better[:, None], z + step, z)
            r = torch.where(better[:, None], r_new, r)
            cost = torch.where(better, cost_new, cost)
            lam = torch.where(better, lam * 0.3, lam * 10.0)
            if better.all():
                break
        if ((previous - cost) <= 1e-8 * previous).all():  # every body has converged
            break
    final = unpack(z)
    with torch.no_grad():
        for k in keys:
            params[k].copy_(final[k])
    return float((cost / r.shape[1] * 3).sum())


def _angles(fittable: Fittable, pose: torch.Tensor) -> torch.Tensor:
    from blsm.joint_limits import angles_from_unconstrained

    return angles_from_unconstrained(pose, fittable.skeleton.dof_limits.to(pose.dtype))
