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

The pure math of the steps is in :mod:`blsm.learn.training.bases`, the per-registration fit (Eq. 5.26) in
:mod:`blsm.learn.training.train_fit`; the registration files are read by
:func:`blsm.learn.registration.registrations.load_registrations`.

Units: metres, radians; errors are reported in millimetres (mean per-vertex Euclidean distance).
"""

from __future__ import annotations

import dataclasses
import datetime
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm import io, skeleton
from blsm.config import config_from_dict
from blsm.lbs import linear_blend_skinning
from blsm.learn.posing import pose
from blsm.learn.training.bases import (
    SYMMETRY_MODES,
    blend_weights,
    blended_transforms,
    bone_mirror_index,
    bone_pca,
    normal_equations,
    shape_pca,
    solve_normal_equations,
    symmetrize_vertices,
    template_bone_lengths,
    weight_support,
)
from blsm.learn.training.train_fit import (
    FitParams,
    LearnedModel,
    TrainFitConfig,
    errors_mm,
    fit_full,
    fit_pose_and_bones,
    posed_model,
    templates,
    unskinned,
)
from blsm.spiral.autodecoder import SpiralConfig


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
class CorrectivesConfig:
    """Bone-corrective blendshapes and mean template (Eq. 5.27)."""

    alternations: int = 2  # rounds of (Eq. 5.26 fit, Eq. 5.27 solve)
    ridge: float = 1e-3  # ridge on P_bc, times the number of registrations

    def __post_init__(self) -> None:
        if self.alternations < 1 or self.ridge < 0:
            raise ValueError("correctives.alternations must be >= 1 and correctives.ridge >= 0")


SHAPE_DECODERS = ("linear", "spiral")


@dataclass
class ShapeConfig:
    """Shape PCA of the T-pose residuals (Eqs. 5.28, 5.8), and optionally BLSM-spiral (Eq. 11).

    ``decoder: spiral`` also learns the spiral decoder of :mod:`blsm.spiral.autodecoder` (settings in
    ``spiral:``) on the same residuals, and the model file's shape space is that decoder
    (:mod:`blsm.spiral.shape`); the PCA basis is still learnt and stored, and it is what the blend
    weights (step 5) and the held-out fit of the report use.
    """

    num_coeffs: int = 16
    symmetry: str = "symmetrize"  # symmetrize | augment
    decoder: str = "linear"  # linear (Eq. 8) | spiral (Eq. 11)
    spiral: SpiralConfig = field(default_factory=SpiralConfig)

    def __post_init__(self) -> None:
        if self.num_coeffs < 1:
            raise ValueError(f"shape.num_coeffs must be >= 1, got {self.num_coeffs}")
        if self.symmetry not in SYMMETRY_MODES:
            raise ValueError(f"shape.symmetry must be one of {', '.join(SYMMETRY_MODES)}, got {self.symmetry!r}")
        if self.decoder not in SHAPE_DECODERS:
            raise ValueError(f"shape.decoder must be one of {', '.join(SHAPE_DECODERS)}, got {self.decoder!r}")


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
    fit: TrainFitConfig = field(default_factory=TrainFitConfig)
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
    """One registration as :func:`learn_model` reads it (``blsm.learn.registration.registrations.Registration`` and
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

# ------------------------------------------------------------------------------------------------
# The pipeline


def _stack(regs: Sequence[Any], device: torch.device) -> tuple[torch.Tensor, FitParams, torch.Tensor]:
    f32 = torch.float32

    def t(name: str) -> torch.Tensor:
        return torch.as_tensor(np.stack([np.asarray(getattr(r, name), dtype=np.float32) for r in regs]), dtype=f32, device=device)

    st = FitParams(t("angles"), torch.zeros(0), t("global_orient"), t("transl"))
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


@dataclass
class _Run:
    """What the steps of :func:`learn_model` share: the initial model (float32, on the device), the
    settings, the random generator and the report, whose ``seconds`` each :meth:`lap` fills."""

    model: Any
    cfg: TrainConfig
    gen: torch.Generator
    report: dict[str, Any]
    mark: float = field(default_factory=time.perf_counter)
    spiral: tuple[dict[str, np.ndarray], dict[str, Any]] | None = None  # model-file arrays and metadata

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.report["seconds"][name] = round(now - self.mark, 2)
        self.mark = now


def learn_model(
    initial_model, registrations: Sequence[Any], config: TrainConfig | None = None,
    on_shape_residuals: Callable[[torch.Tensor], None] | None = None,
) -> tuple[io.ModelData, dict]:
    """Learn b_mean, P_b, V_mean, P_bc, P_s and W from registrations (Eqs. 5.26-5.31).

    Args:
        initial_model: a :class:`blsm.BLSM` (the packaged one): template, skeleton, weights.
        registrations: objects with ``vertices`` (V, 3), ``bone_scales`` (J,), ``angles`` (47,),
            ``global_orient`` (3,), ``transl`` (3,) (numpy or torch) and ``meta`` (dict; see
            :func:`is_rest_pose`; ``split`` "test" registrations are only evaluated).
        config: :class:`TrainConfig` (defaults if None).
        on_shape_residuals: called once with the (N, V, 3) T-pose residuals that a shape decoder is
            learnt from (:func:`shape_residuals`), e.g. to train several spiral decoders on them
            (``experiments/shape_space/blsm_spiral_fig4.py``).

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
    kb = cfg.bone.num_coeffs
    if len(rest) < max(kb, 2) + 1:
        raise ValueError(f"need more than {max(kb, 2)} rest-pose training registrations for {kb} bone "
                         f"coefficients, got {len(rest)}")
    counts = {"train_rest": len(rest), "train_posed": len(posed), "test": len(test)}
    run = _Run(model, cfg, gen, {"registrations": counts, "seconds": {}, "errors_mm": {}})
    t_all = run.mark
    targets_all, st_all, scales_all = _stack(registrations, device)
    _log(f"{len(rest)} rest-pose and {len(posed)} posed training registrations, {len(test)} test")

    ridx = torch.as_tensor(rest, device=device)
    mdl, st_all.bone = _bone_basis(run, scales_all, ridx)
    st_rest = _correctives(run, mdl, targets_all[ridx], st_all.take(ridx))
    st_rest, unposed = _shape_basis(run, mdl, targets_all[ridx], st_rest)
    if cfg.shape.decoder == "spiral" or on_shape_residuals is not None:
        resid = shape_residuals(model, mdl, unposed, st_rest, cfg.shape.symmetry)
        if on_shape_residuals is not None:
            on_shape_residuals(resid)
        if cfg.shape.decoder == "spiral":
            run.spiral = _spiral_decoder(run, resid, len(rest))

    # 5. Blend weights (Eqs. 5.30, 5.31) from the posed training registrations.
    if cfg.weights.enabled and posed:
        mdl.weights = _learn_weights(
            model, mdl, metas, rest, posed, st_rest, unposed, targets_all, st_all, cfg, run.report, gen
        )
        run.lap("weights")
    else:
        run.report["weights"] = {"skipped": True}

    # Population coefficients; held-out evaluation.
    if test:
        tidx = torch.as_tensor(test, device=device)
        st_test = fit_full(model, mdl, targets_all[tidx], st_all.take(tidx), cfg.fit, generator=gen)
        terr = errors_mm(model, mdl, targets_all[tidx], st_test, cfg.fit.batch_size)
        run.report["errors_mm"]["test"] = float(terr.mean())
        run.lap("test")
        _log(f"held-out ({len(test)} registrations): {float(terr.mean()):.2f} mm")
    run.report["seconds"]["total"] = round(time.perf_counter() - t_all, 2)
    data = _assemble(initial_model, mdl, st_rest, run.report, cfg)
    if run.spiral is not None:
        data.arrays.update(run.spiral[0])
        data.meta["shape_decoder"] = run.spiral[1]
    return data, run.report


def _bone_basis(run: _Run, scales_all: torch.Tensor, ridx: torch.Tensor) -> tuple[LearnedModel, torch.Tensor]:
    """1. Bone basis (Sec. 5.4.2) from the rest-pose training registrations ``ridx``.

    Returns:
        The model to learn (bind skeleton and template rebased or kept, b_mean, P_b, zero
        correctives) and the initial c_b (N, Kb) of every registration: its stage-1 bone lengths
        (``scales_all`` (N, J) times the initial skeleton's) projected on the basis.
    """
    model, kb, report = run.model, run.cfg.bone.num_coeffs, run.report
    mirror = model.vertex_mirror
    bmir = bone_mirror_index(model.bone_names)
    lengths0 = template_bone_lengths(model)  # (J,) of the initial skeleton
    lengths = scales_all[ridx].double() * lengths0.double()
    pca = bone_pca(lengths, kb, bmir)
    mean_scale_old = (pca.mean_lengths / lengths0.double()).float()  # b_mean on the initial skeleton
    if run.cfg.bone.rebase_skeleton:
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
    _log(f"bone PCA: first 3 components explain {100 * report['bone_pca_explained_first3']:.2f} % of "
         "bone-length variance")
    zeros = torch.zeros(kb, model.num_vertices, 3, device=scales_all.device)
    mdl = LearnedModel(heads.float(), template.float(), model.weights.clone(), b_mean, p_b, zeros)
    bone = pca.project(scales_all.double() * lengths0.double()).float()
    run.lap("bone_basis")
    return mdl, bone


def _correctives(run: _Run, mdl: LearnedModel, tgt_rest: torch.Tensor, st_rest: FitParams) -> FitParams:
    """2 + 3. Alternate Eq. 5.26 (fit) and Eq. 5.27 (solve) on the rest-pose training registrations;
    ``mdl``'s template and correctives are replaced. Returns the fitted parameters."""
    model, cfg, report = run.model, run.cfg, run.report
    mirror, bs, n = model.vertex_mirror, cfg.fit.batch_size, len(tgt_rest)
    for a in range(cfg.correctives.alternations):
        st_rest = fit_pose_and_bones(model, mdl, tgt_rest, st_rest, cfg.fit, generator=run.gen)
        err = float(errors_mm(model, mdl, tgt_rest, st_rest, bs).mean())
        report["errors_mm"][f"fit_{a}"] = err
        run.lap(f"fit_{a}")
        _log(f"alternation {a}: Eq. 5.26 fit, training error {err:.2f} mm "
             f"({report['seconds'][f'fit_{a}']:.1f} s)")
        normal = rhs = None
        with torch.no_grad():
            for s in range(0, n, bs):
                sub = st_rest.take(slice(s, s + bs))
                tr = posed_model(model, mdl, sub, idx=torch.arange(1, device=tgt_rest.device)).transforms
                m, t = blended_transforms(mdl.weights, tr)
                nrm, r = normal_equations(tgt_rest[s : s + bs], sub.bone, m, t)
                normal = nrm if normal is None else normal + nrm
                rhs = r if rhs is None else rhs + r
            vbar, pbc = solve_normal_equations(normal, rhs, cfg.correctives.ridge * n)
        mdl.template = symmetrize_vertices(vbar, mirror).float()
        mdl.correctives = symmetrize_vertices(pbc, mirror).float()
        err = float(errors_mm(model, mdl, tgt_rest, st_rest, bs).mean())
        report["errors_mm"][f"correctives_{a}"] = err
        run.lap(f"correctives_{a}")
        _log(f"alternation {a}: Eq. 5.27 solve, training error {err:.2f} mm "
             f"({report['seconds'][f'correctives_{a}']:.1f} s)")
    return st_rest


def _shape_basis(
    run: _Run, mdl: LearnedModel, tgt_rest: torch.Tensor, st_rest: FitParams
) -> tuple[FitParams, torch.Tensor]:
    """4. Shape PCA of the T-pose residuals (Eqs. 5.28, 5.8); ``mdl``'s template and shape basis are
    set. Returns the parameters with their c_s and the un-skinned registrations (N, V, 3)."""
    model, ks, bs, report = run.model, run.cfg.shape.num_coeffs, run.cfg.fit.batch_size, run.report
    mirror, device = model.vertex_mirror, tgt_rest.device
    unposed = unskinned(model, mdl, tgt_rest, st_rest, bs)
    resid = unposed - templates(mdl, dataclasses.replace(st_rest, shape=None), None, None)
    smean, sbasis, c_s, sexpl = shape_pca(resid, ks, mirror, run.cfg.shape.symmetry)
    mdl.template = symmetrize_vertices(mdl.template + smean.float(), mirror)
    mdl.shape_basis = sbasis.float()
    st_rest = dataclasses.replace(st_rest, shape=c_s.float())
    if sbasis.shape[0] < ks:
        _log(f"shape PCA: only {sbasis.shape[0]} components (fewer samples than {ks}); padding with zeros")
        pad = torch.zeros(ks - sbasis.shape[0], *sbasis.shape[1:], device=device)
        mdl.shape_basis = torch.cat([mdl.shape_basis, pad])
        zeros = torch.zeros(len(tgt_rest), ks - sbasis.shape[0], device=device)
        st_rest.shape = torch.cat([st_rest.shape, zeros], 1)
        sexpl = torch.cat([sexpl, sexpl.new_zeros(ks - len(sexpl))])
    report["shape_pca_explained"] = [float(x) for x in sexpl]
    err = float(errors_mm(model, mdl, tgt_rest, st_rest, bs).mean())
    report["errors_mm"]["shape"] = err
    run.lap("shape_basis")
    _log(f"shape PCA ({ks} components, {100 * float(sexpl.sum()):.1f} % of residual variance): "
         f"training error {err:.2f} mm")
    return st_rest, unposed


def shape_residuals(model, mdl: LearnedModel, unposed: torch.Tensor, st_rest: FitParams,
                    symmetry: str) -> torch.Tensor:
    """The T-pose residuals V_D^n (Eq. 5.28) of step 4 relative to the final template (``mdl.template``
    holds the PCA mean by then), symmetrised or mirror-augmented as ``symmetry`` says (as the PCA
    saw them). (N, V, 3) metres (2N with ``augment``: the mirror images after the originals)."""
    resid = unposed - templates(mdl, dataclasses.replace(st_rest, shape=None), None, None)
    sym = symmetrize_vertices(resid.double(), model.vertex_mirror).float()
    return sym if symmetry == "symmetrize" else torch.cat([resid, 2 * sym - resid])


def _spiral_decoder(run: _Run, resid: torch.Tensor, n: int) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """4b. BLSM-spiral (Eqs. 11, 17): the auto-decoder on :func:`shape_residuals`; the first ``n``
    codes are the training bodies'. Returns the model-file arrays and metadata."""
    from blsm.spiral.autodecoder import train_auto_decoder
    from blsm.spiral.hierarchy import body_hierarchy
    from blsm.spiral.shape import decoder_arrays

    cfg = run.cfg.shape.spiral
    ops = body_hierarchy(run.model, cfg.settings())
    _log(f"spiral decoder: latent {cfg.latent}, levels {ops.sizes}, {len(resid)} bodies, {cfg.epochs} epochs")
    dec, codes, rep = train_auto_decoder(resid, ops, cfg)
    run.report["spiral"] = rep
    run.lap("spiral")
    _log(f"spiral decoder: training error {rep['train_error_mm']:.2f} mm on the residuals "
         f"({run.report['seconds']['spiral']:.1f} s)")
    return decoder_arrays(dec, ops, codes[:n], rep)


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
            base[k] = unposed[r] - templates(mdl, sub, None, None)[0]
            have[k] = True
    st = FitParams(st.angles, bone, st.global_orient, st.transl, shape)
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
            err0 = errors_mm(model, cur, tgt, st, bs, base=base)
            report["errors_mm"]["posed_before_weights"] = float(err0.mean())
        with torch.no_grad():  # fixed per-registration transforms: theta, c_b do not change here
            trs, tmpls = [], []
            for s in range(0, n, bs):
                sub = st.take(slice(s, s + bs))
                trs.append(posed_model(model, cur, sub, idx=torch.arange(1, device=device)).transforms)
                tmpls.append(templates(cur, sub, None, base[s : s + bs]))
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
        _log(f"weights: round {rnd}, posed training error {float(errors_mm(model, cur, tgt, st, bs, base=base, weights=w).mean()):.2f} mm")
    with torch.no_grad():
        if wc.prune_below > 0:
            w = torch.where(w < wc.prune_below, torch.zeros_like(w), w)
            w = w / w.sum(1, keepdim=True)
    st = fit_pose_and_bones(model, dataclasses.replace(mdl, weights=w), tgt, st, cfg.fit, base=base, generator=gen)
    err1 = errors_mm(model, mdl, tgt, st, bs, base=base, weights=w)
    report["errors_mm"]["posed_after_weights"] = float(err1.mean())
    report["weights"] = {"support_per_vertex": float(mask.sum(1).float().mean()), "max_change": float((w - w0).abs().max()), "seconds": round(time.perf_counter() - t0, 2)}
    _log(f"weights: posed training error {float(err0.mean()):.2f} -> {float(err1.mean()):.2f} mm")
    return w.detach()


def _assemble(initial_model, mdl: LearnedModel, st_rest: FitParams, report: dict, cfg: TrainConfig) -> io.ModelData:
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
    meta.pop("shape_decoder", None)  # an initial BLSM-spiral's decoder is not carried over (learn_model adds its own)
    meta["name"] = "blsm-learned"
    meta["built"] = datetime.date.today().isoformat()
    meta["train_report"] = report
    meta["train_config"] = dataclasses.asdict(cfg)
    return io.ModelData(arrays=arrays, meta=meta, dof_table_yaml=src.dof_table.source)
