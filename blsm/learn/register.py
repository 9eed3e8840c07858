"""Registering the BLSM template to scans (thesis Sec. 5.4.1, Eqs. 5.13-5.25).

Two stages per scan, batched over scans:

1. :func:`fit_landmarks` (Eq. 5.13): joint angles theta (through the unconstrained x of Eq. 5.6, so
   the limits always hold), per-bone global scales b (through log b, so they stay positive), global
   orientation and translation minimising the landmark distances of the posed template. The global
   rigid motion is initialised by Procrustes on the trunk landmarks, then L-BFGS refines everything.
2. :func:`refine` (Eqs. 5.14-5.25): free per-vertex displacements V_D in the T-pose frame,
   ``S^ = LBS(V_T + V_D, T(s, theta))`` with the stage-1 skeleton held fixed, minimising
   ``E_data + E_smoothness + E_reg + E_rigid`` with Adam.

Normalisation (checked for metre units): every term is a *mean* over its elements (MNN pairs,
located landmarks, vertices, edges), as PyTorch3D's losses (which the thesis used) are. The counts
are of the same order (about 7k vertices, 21k edges, 5k-10k MNN pairs), so the thesis' relative
weights keep their meaning, and the loss of one scan does not depend on how many scans share a
batch. Note that in metres the edge-length term of Eq. 5.24 (squared lengths, about 1e-4 m^2) is
tiny; it is kept as written. For the same reason lambda_EV is 3.0, not the thesis' 0.003 (see
:class:`RegisterConfig`).

Engineering additions (switchable, ``shape_init``/``surface_rounds``): stage 1 also fits the initial
model's shape coefficients to the landmarks, and :func:`fit_surface` refines skeleton + shape on the
scan surface (MNN + landmarks) before stage 2. The skeleton-only landmark fit of Eq. 5.13 cannot
move soft-tissue landmarks (chest, belly, back): on Anny scans its landmark RMS stays at about 12 mm
even with exact landmarks and a Gauss-Newton solver started at the true pose, i.e. that is the
model's floor, not slow convergence.

Mutual nearest neighbours (Eq. 5.16) are found with ``scipy.spatial.cKDTree`` on the CPU on fresh
surface samples every ``mnn_refresh`` iterations; between refreshes the samples (faces and
barycentric coordinates on S^) and the pairs are kept, while the model samples move with V_D, so
the gradients still reach the vertices.

Units and conventions: metres, radians, Y up, the body faces +Z at rest, +X is the body's left.
"""

from __future__ import annotations

import argparse
import dataclasses
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

from blsm.io import atomic_write, read_npz, read_yaml
from blsm.joint_limits import unconstrained_from_angles
from blsm.learn.posing import pose
from blsm.mesh import vertex_normals

FORMAT = "blsm-registration"
FORMAT_VERSION = 1
DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "blsm" / "register.yaml"

# Bones whose landmarks fix the global rigid motion before the articulated fit.
TRUNK_BONES: tuple[str, ...] = ("pelvis", "spine_01", "spine_02", "spine_03", "hip_l", "hip_r")
HAND_BONES: tuple[str, ...] = ("wrist_l", "wrist_r")


# ------------------------------------------------------------------------------------------------
# Configuration and results


@dataclass
class RegisterConfig:
    """Settings of both stages (YAML keys are the field names; unknown keys are errors).

    Attributes:
        stage1_iterations: L-BFGS iterations of the articulated landmark fit (Eq. 5.13).
        stage1_rigid_iterations: L-BFGS iterations on global orientation/translation only, first.
        angle_prior: weight (m^2 per rad^2) of mean(theta^2), pulling unconstrained angles to 0.
        scale_prior: weight (m^2) of mean(log(b / b_mean)^2), pulling bone scales to the mean.
        symmetry_prior: weight (m^2) of mean((log b_left - log b_right)^2); 0 disables it.
        shape_init: engineering addition (not in the thesis): also fit the initial model's shape
            coefficients (Eq. 8) in stage 1 and in :func:`fit_surface`; stage 2 then starts from
            ``V_T + V_s`` (the reported V_D includes V_s). False gives the thesis' pipeline.
        stage1_shape_iterations: L-BFGS iterations of the landmark fit with shape, after the
            skeleton-only fit.
        shape_prior: weight (m^2) of mean(c_s^2) (coefficients are in standard deviations).
        surface_rounds, surface_iterations: ICP rounds (fresh MNN pairs) and L-BFGS iterations per
            round of :func:`fit_surface` (engineering addition); 0 skips it.
        iterations: Adam iterations of the free-form refinement (Eq. 5.14).
        lr: Adam learning rate on V_D, metres (thesis: 0.005).
        lr_decay: factor applied to the learning rate on a plateau (thesis: 0.9).
        plateau_patience: iterations without a 0.1 % improvement of the loss before decaying.
        scan_samples: points sampled on the scan surface per refresh (thesis: 50k; 20k here keeps a
            scan at a few seconds on one core).
        model_samples: points sampled on S^ per refresh (thesis: 20k; 8k here, same reason).
        mnn_refresh: iterations between fresh samples and MNN pairs (1 = every iteration).
        lambda_mnn, lambda_lm: data-term weights of Eq. 5.15.
        lambda_smoothness: Eq. 5.21. lambda_ev, lambda_el: Eq. 5.22. lambda_rigid: Eq. 5.25.
            lambda_ev deviates from the thesis (0.003 there, 3.0 here): with metres and mean
            normalisation 0.003 leaves E_EV negligible, vertices slide along the surface and the
            correspondence error grows (measured on an Anny scan: 0.1 -> 8.5 mm, 1 -> 4.8 mm,
            3 -> 4.4 mm, 10 -> 4.5 mm, 30 -> 4.9 mm mean error vs ground truth).
        mnn_tangent_weight: weight in [0, 1] of the part of each MNN residual along the scan
            surface in stage 2 (1 = Eq. 5.15's point-to-point distance, the thesis; 0 = point-to-
            plane, the distance along the scan normal only). Random surface samples are about 1 cm
            apart at 20k samples, so a point-to-point pair also pulls across the surface; measured
            on 18 held-out scans of the default population (``benchmarks/registration_floor.py``):
            4.23 mm mean error at 1, 4.05 mm at 0. The default stays the thesis' term, with
            which the packaged model was made.
        normalisation: "mean" (every term a mean over its elements, as PyTorch3D's losses) or
            "sum" (sums over elements, divided by the template's vertex count V for readable
            numbers; Adam does not see a common factor).
        seed: random seed of the surface sampling.
    """

    stage1_iterations: int = 300
    stage1_rigid_iterations: int = 20
    angle_prior: float = 1e-6
    scale_prior: float = 1e-5
    symmetry_prior: float = 0.0
    shape_init: bool = True
    stage1_shape_iterations: int = 200
    shape_prior: float = 1e-5
    surface_rounds: int = 6
    surface_iterations: int = 15
    iterations: int = 150
    lr: float = 0.005
    lr_decay: float = 0.9
    plateau_patience: int = 5
    scan_samples: int = 20_000
    model_samples: int = 8_000
    mnn_refresh: int = 5
    lambda_mnn: float = 1.0
    lambda_lm: float = 1.0
    lambda_smoothness: float = 0.007
    lambda_ev: float = 3.0
    lambda_el: float = 0.02
    lambda_rigid: float = 0.01
    normalisation: str = "mean"
    mnn_tangent_weight: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("stage1_iterations", "stage1_rigid_iterations", "stage1_shape_iterations",
                     "iterations", "surface_rounds", "surface_iterations", "mnn_refresh",
                     "scan_samples", "model_samples", "plateau_patience"):
            v = getattr(self, name)
            if v < (1 if name in ("mnn_refresh", "scan_samples", "model_samples", "plateau_patience") else 0):
                raise ValueError(f"{name} must be positive, got {v}")
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and (not math.isfinite(v) or v < 0):
                raise ValueError(f"{f.name} must be finite and >= 0, got {v}")
        if self.normalisation not in ("mean", "sum"):
            raise ValueError(f"normalisation must be 'mean' or 'sum', got {self.normalisation!r}")
        if self.mnn_tangent_weight > 1:
            raise ValueError(f"mnn_tangent_weight must be in [0, 1], got {self.mnn_tangent_weight}")
        if not 0 < self.lr_decay <= 1:
            raise ValueError(f"lr_decay must be in (0, 1], got {self.lr_decay}")


def load_config(path: str | Path) -> RegisterConfig:
    """Read a :class:`RegisterConfig` from YAML; unknown keys and wrong types are one-line errors."""
    from blsm.config import config_from_dict

    return config_from_dict(RegisterConfig, read_yaml(path, "registration config"), str(path))


@dataclass
class LandmarkSelection:
    """The selection operator A_lm of Eqs. 5.13 and 5.15: named points on the template surface.

    Attributes:
        names: the L landmark names.
        vertices: (L, 3) template vertex indices of each point's triangle (or the vertex thrice).
        bary: (L, 3) barycentric weights, rows sum to 1.
    """

    names: list[str]
    vertices: torch.Tensor
    bary: torch.Tensor

    @classmethod
    def from_index(cls, names: Sequence[str], index: Any, faces: torch.Tensor | None = None,
                   bary: Any = None) -> LandmarkSelection:
        """Build from (L,) vertex indices, or from (L,) face indices with (L, 3) barycentrics."""
        idx = torch.as_tensor(np.asarray(index), dtype=torch.long)
        names = [str(n) for n in names]
        if idx.dim() != 1 or idx.shape[0] != len(names):
            raise ValueError(f"landmark index must be (L,) with L = {len(names)} names, got {tuple(idx.shape)}")
        if bary is None:
            return cls(names, idx[:, None].expand(-1, 3).clone(), torch.tensor([[1.0, 0.0, 0.0]]).expand(len(names), 3).clone())
        if faces is None:
            raise ValueError("face landmarks need the model's faces")
        w = torch.as_tensor(np.asarray(bary), dtype=torch.float32)
        if w.shape != (len(names), 3):
            raise ValueError(f"landmark bary must be (L, 3), got {tuple(w.shape)}")
        return cls(names, faces[idx].long(), w)

    def __len__(self) -> int:
        return len(self.names)

    def select(self, points: torch.Tensor) -> torch.Tensor:
        """A_lm: (B, V, 3) mesh vertices -> (B, L, 3) landmark positions."""
        w = self.bary.to(points.dtype)
        return (points[:, self.vertices] * w[..., None]).sum(2)


@dataclass
class Stage1:
    """Result of :func:`fit_landmarks` (Eq. 5.13), batched.

    Attributes:
        bone_scales: (B, J) global bone scales b. angles: (B, 47) radians.
        global_orient: (B, 3) axis-angle. transl: (B, 3) metres.
        landmark_error: (B,) RMS landmark distance in metres over the located landmarks.
    """

    bone_scales: torch.Tensor
    angles: torch.Tensor
    global_orient: torch.Tensor
    transl: torch.Tensor
    landmark_error: torch.Tensor
    shape: torch.Tensor | None = None
    shape_offsets: torch.Tensor | None = None


@dataclass
class Registration:
    """One registered scan in BLSM topology ("blsm-registration" v1).

    Attributes:
        vertices: (V, 3) the registered, posed mesh S^ (Eq. 5.14's result), metres, world frame.
        bone_scales: (J,) global bone scales b.
        angles: (47,) atom angles, radians.
        global_orient: (3,) axis-angle. transl: (3,) metres.
        displacement: (V, 3) V_D in the T-pose frame: ``S^ = LBS(V_T + V_D, T(b, theta))``.
        meta: scan id, subject, pose id, split, errors in mm, iterations, seconds.
    """

    vertices: np.ndarray
    bone_scales: np.ndarray
    angles: np.ndarray
    global_orient: np.ndarray
    transl: np.ndarray
    displacement: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)


_REG_ARRAYS: dict[str, tuple[str, ...]] = {
    "vertices": ("V", "3"),
    "bone_scales": ("J",),
    "angles": ("D",),
    "global_orient": ("3",),
    "transl": ("3",),
    "displacement": ("V", "3"),
}


def save_registration(reg: Registration, path: str | Path) -> Path:
    """Write a "blsm-registration" v1 ``.npz`` atomically (float32 arrays)."""
    path = Path(path)
    arrays = {k: np.asarray(getattr(reg, k), dtype=np.float32) for k in _REG_ARRAYS}
    _check_registration(arrays, str(path))
    with atomic_write(path) as fh:
        np.savez_compressed(
            fh,
            format=np.array(FORMAT),
            format_version=np.array(FORMAT_VERSION),
            meta=np.array(json.dumps(reg.meta, sort_keys=True)),
            **arrays,
        )
    return path


def load_registration(path: str | Path) -> Registration:
    """Read and validate a "blsm-registration" v1 file; errors are one line naming the file."""
    path = Path(path)
    raw = read_npz(path, "registration")
    fmt = str(raw["format"]) if "format" in raw else None
    if fmt != FORMAT:
        raise ValueError(f"{path}: not a BLSM registration file (format={fmt!r})")
    try:
        version = int(raw["format_version"])
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{path}: bad or missing format_version") from None
    if version != FORMAT_VERSION:
        raise ValueError(f"{path}: format_version {version} is not supported (expected {FORMAT_VERSION})")
    missing = [k for k in (*_REG_ARRAYS, "meta") if k not in raw]
    if missing:
        raise ValueError(f"{path}: missing arrays {missing}")
    try:
        meta = json.loads(str(raw["meta"]))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: meta is not JSON ({exc})") from None
    arrays = {k: raw[k].astype(np.float32) for k in _REG_ARRAYS}
    _check_registration(arrays, str(path))
    return Registration(**arrays, meta=meta)


def _check_registration(arrays: dict[str, np.ndarray], where: str) -> None:
    dims: dict[str, int] = {"3": 3}
    for k, shape in _REG_ARRAYS.items():
        a = arrays[k]
        if a.ndim != len(shape) or any(dims.setdefault(n, s) != s for n, s in zip(shape, a.shape)):
            raise ValueError(f"{where}: array {k!r} has shape {a.shape}, expected {shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"{where}: array {k!r} is not finite")


def correspondence_error(reg: Registration, gt_points: Any) -> tuple[float, float]:
    """Mean and max per-vertex distance in millimetres between ``reg.vertices`` and ground truth.

    Args:
        reg: a registration (or anything with ``vertices`` (V, 3) metres).
        gt_points: (V, 3) true positions of the template vertices on the scan, metres.

    Returns:
        (mean_mm, max_mm).
    """
    v = np.asarray(reg.vertices, dtype=np.float64)
    g = np.asarray(gt_points, dtype=np.float64)
    if v.shape != g.shape:
        raise ValueError(f"gt_points must be {v.shape}, got {g.shape}")
    d = np.linalg.norm(v - g, axis=1) * 1000.0
    return float(d.mean()), float(d.max())


# ------------------------------------------------------------------------------------------------
# Mesh operators (pure functions)


def mesh_edges(faces: torch.Tensor) -> torch.Tensor:
    """Unique undirected edges (E, 2), ``i < j``, of a triangle mesh's faces (F, 3)."""
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).long()
    e = torch.sort(e, dim=1).values
    return torch.unique(e, dim=0)


def uniform_laplacian(vertices: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Eqs. 5.17-5.20 with uniform weights: ``delta_i = mean_{j in N(i)} v_j - v_i``.

    Args:
        vertices: (B, V, 3). edges: (E, 2) undirected edges.

    Returns:
        (B, V, 3) Laplacian vectors (0 for isolated vertices).
    """
    n = vertices.shape[1]
    i, j = edges[:, 0], edges[:, 1]
    deg = torch.bincount(torch.cat([i, j]), minlength=n).to(vertices.dtype)
    acc = torch.zeros_like(vertices)
    acc = acc.index_add(1, i, vertices[:, j]).index_add(1, j, vertices[:, i])
    mean = acc / deg.clamp(min=1)[None, :, None]
    return torch.where(deg[None, :, None] > 0, mean - vertices, torch.zeros_like(vertices))


def edge_vectors(vertices: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Eq. 5.23: (B, V, 3), (E, 2) -> (B, E, 3) edge vectors ``v_i - v_j``."""
    return vertices[:, edges[:, 0]] - vertices[:, edges[:, 1]]


def edge_lengths_sq(vertices: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Eq. 5.24: (B, V, 3), (E, 2) -> (B, E) squared edge lengths, m^2."""
    return edge_vectors(vertices, edges).square().sum(-1)


def edge_terms(vertices: torch.Tensor, target: torch.Tensor, edges: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean edge-vector and edge-length discrepancies of Eqs. 5.22 and 5.25.

    Args:
        vertices: (B, V, 3) current mesh S^. target: (B, V, 3) reference S^_T. edges: (E, 2).

    Returns:
        ((B,) mean_e ||EV - EV_T||^2 in m^2, (B,) mean_e (EL - EL_T)^2 in m^4).
    """
    if edges.shape[0] == 0:
        z = vertices.new_zeros(vertices.shape[0])
        return z, z
    ev = (edge_vectors(vertices, edges) - edge_vectors(target, edges)).square().sum(-1).mean(-1)
    el = (edge_lengths_sq(vertices, edges) - edge_lengths_sq(target, edges)).square().mean(-1)
    return ev, el


def mutual_nearest_neighbours(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 5.16: index pairs (ia, ib) with ``NN(a[ia], b) == ib`` and ``NN(b[ib], a) == ia``.

    Args:
        a: (N, 3) points. b: (M, 3) points.

    Returns:
        ia (P,), ib (P,) int64, sorted by ia.
    """
    from scipy.spatial import cKDTree

    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    nn_ab = cKDTree(b).query(a, k=1)[1]  # (N,) nearest b of each a
    nn_ba = cKDTree(a).query(b, k=1)[1]  # (M,) nearest a of each b
    ia = np.nonzero(nn_ba[nn_ab] == np.arange(len(a)))[0]
    return ia.astype(np.int64), nn_ab[ia].astype(np.int64)


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform random points on a triangle mesh.

    Args:
        vertices: (V, 3). faces: (F, 3). n: number of samples. rng: numpy generator.

    Returns:
        face indices (n,) and barycentric weights (n, 3).
    """
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    p = area / area.sum()
    fi = rng.choice(len(faces), size=n, p=p)
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    bary = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=1)
    return fi, bary


# ------------------------------------------------------------------------------------------------
# Stage 1: landmark fit (Eq. 5.13)


def _kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising ||R src + t - dst||^2 (both (N, 3))."""
    from scipy.spatial.transform import Rotation

    cs, cd = src.mean(0), dst.mean(0)
    if len(src) < 3:
        return np.zeros(3), cd - cs
    rot, _ = Rotation.align_vectors(dst - cd, src - cs)
    return rot.as_rotvec(), cd - rot.apply(cs)


def fit_landmarks(
    model,
    landmarks: torch.Tensor,
    selection: LandmarkSelection,
    config: RegisterConfig | None = None,
) -> Stage1:
    """Eq. 5.13: fit angles, bone scales and the global rigid motion to landmarks.

    Args:
        model: a :class:`blsm.BLSM` (float32 or float64).
        landmarks: (B, L, 3) target landmark positions in metres, in ``selection`` order; a row of
            NaN means the landmark was not located and is ignored.
        selection: the template landmarks A_lm.
        config: settings (defaults if None).

    Returns:
        :class:`Stage1` (detached).
    """
    cfg = config or RegisterConfig()
    dtype = model.template.dtype
    if landmarks.dim() != 3 or landmarks.shape[1:] != (len(selection), 3):
        raise ValueError(f"landmarks must be (B, {len(selection)}, 3), got {tuple(landmarks.shape)}")
    x_lm = landmarks.to(dtype)
    mask = torch.isfinite(x_lm).all(-1)  # (B, L)
    if (mask.sum(1) < 3).any():
        raise ValueError("every scan needs at least 3 located landmarks")
    x_lm = torch.where(mask[..., None], x_lm, torch.zeros_like(x_lm))
    bsz, n_lm = mask.shape
    # Only the landmark triangles need skinning: LBS is per vertex.
    vidx = selection.vertices.reshape(-1)
    sub_t = model.template[vidx]  # (3L, 3)
    sub_w = model.weights[vidx]  # (3L, J)
    bary = selection.bary.to(dtype)

    use_shape = cfg.shape_init and model.num_shape_coeffs > 0
    beta = torch.zeros(bsz, model.num_shape_coeffs, dtype=dtype, requires_grad=use_shape)

    def shape_offsets(c: torch.Tensor) -> torch.Tensor:
        return model.shape_decoder(c)  # (B, V, 3), Eq. 8

    def posed_landmarks(b, theta_or_x, go, tr, is_x=True, c=None):
        kw = {"pose": theta_or_x} if is_x else {"angles": theta_or_x}
        tmpl = sub_t if c is None else sub_t + shape_offsets(c)[:, vidx]
        v = pose(model, tmpl, bone_scales=b, global_orient=go, transl=tr, weights=sub_w, **kw).vertices
        return (v.reshape(-1, n_lm, 3, 3) * bary[..., None]).sum(2)  # (B, L, 3)

    # Procrustes of the rest template's landmarks on the scan's (trunk landmarks when enough).
    rest = posed_landmarks(model.bone_mean[None], torch.zeros(1, model.num_dofs, dtype=dtype), None, None, False)[0]
    bone_of = model.vertex_bones[selection.vertices[:, 0]]
    trunk = torch.tensor([model.bone_names[int(j)] in TRUNK_BONES for j in bone_of])
    go0 = torch.zeros(bsz, 3, dtype=dtype)
    for n in range(bsz):
        use = mask[n] & trunk if int((mask[n] & trunk).sum()) >= 4 else mask[n]
        rv, _ = _kabsch(rest[use].double().numpy(), x_lm[n, use].double().numpy())
        go0[n] = torch.as_tensor(rv, dtype=dtype)
    theta0 = torch.zeros(bsz, model.num_dofs, dtype=dtype)
    with torch.no_grad():
        p0 = posed_landmarks(model.bone_mean.expand(bsz, -1), theta0, go0, None, False)
        w = mask[..., None].to(dtype)
        tr0 = ((x_lm - p0) * w).sum(1) / w.sum(1)

    # An angle on a limit would start where tanh is flat (not the case for the packaged model).
    x = unconstrained_from_angles(theta0, model.dof_limits, eps=0.1).clone().requires_grad_(True)
    log_b = model.bone_mean.log().expand(bsz, -1).clone().requires_grad_(True)
    go = go0.clone().requires_grad_(True)
    tr = tr0.clone().requires_grad_(True)
    counts = mask.sum(1).to(dtype)
    names = model.bone_names
    pairs = [(names.index(n), names.index(n[:-2] + "_r")) for n in names if n.endswith("_l")]
    li = torch.tensor([p[0] for p in pairs])
    ri = torch.tensor([p[1] for p in pairs])

    def loss_fn(with_priors: bool) -> torch.Tensor:
        b = log_b.exp()
        p = posed_landmarks(b, x, go, tr, c=beta if use_shape else None)
        d2 = ((p - x_lm).square().sum(-1) * mask).sum(1) / counts  # (B,) Eq. 5.13, mean over located
        loss = d2.sum()
        if with_priors:
            theta = pose_angles(model, x)
            loss = loss + cfg.angle_prior * theta.square().mean(1).sum()
            loss = loss + cfg.scale_prior * (log_b - model.bone_mean.log()).square().mean(1).sum()
            if cfg.symmetry_prior > 0:
                loss = loss + cfg.symmetry_prior * (log_b[:, li] - log_b[:, ri]).square().mean(1).sum()
            if use_shape:
                loss = loss + cfg.shape_prior * beta.square().mean(1).sum()
        return loss

    def run(params, iters, with_priors):
        if iters <= 0:
            return
        opt = torch.optim.LBFGS(params, lr=1.0, max_iter=iters, line_search_fn="strong_wolfe",
                                tolerance_grad=1e-12, tolerance_change=1e-15, history_size=20)

        def closure():
            opt.zero_grad()
            loss = loss_fn(with_priors)
            loss.backward()
            return loss

        opt.step(closure)

    run([go, tr], cfg.stage1_rigid_iterations, False)
    run([x, log_b, go, tr], cfg.stage1_iterations, True)
    if use_shape:
        # Engineering addition (not in the thesis): the initial model's shape space, fitted with
        # the skeleton, moves soft-tissue landmarks (belly, chest, back) that bone scales cannot.
        run([beta, x, log_b, go, tr], cfg.stage1_shape_iterations, True)
    with torch.no_grad():
        b = log_b.exp()
        p = posed_landmarks(b, x, go, tr, c=beta if use_shape else None)
        rms = (((p - x_lm).square().sum(-1) * mask).sum(1) / counts).sqrt()
        offs = shape_offsets(beta) if use_shape else torch.zeros(bsz, *model.template.shape, dtype=dtype)
        return Stage1(b.detach(), pose_angles(model, x).detach(), go.detach(), tr.detach(), rms,
                      beta.detach(), offs.detach())


def pose_angles(model, x: torch.Tensor) -> torch.Tensor:
    """Eq. 5.6: (B, 47) unconstrained values -> angles in radians inside the model's limits."""
    from blsm.joint_limits import angles_from_unconstrained

    return angles_from_unconstrained(x, model.dof_limits.to(x.dtype))


def _mnn_pairs(scans, current: np.ndarray, faces: torch.Tensor, cfg: RegisterConfig, rng, dtype,
               scan_normals: Sequence[np.ndarray] | None = None):
    """Fresh surface samples and their mutual nearest neighbours (Eq. 5.16) for every scan.

    Model samples are kept as (faces (P, 3), barycentrics (P, 3)) on the current meshes
    ``current`` (B, V, 3), so they move with the vertices; scan samples as points (P, 3).

    Returns:
        per scan ``(faces, barycentrics, scan points, number of pairs, scan normals)``; the unit
        normals (P, 3) at the scan samples (interpolated from ``scan_normals``, each scan's (N, 3)
        vertex normals) only when those are given, else None.
    """
    faces_np = faces.numpy()
    pairs = []
    for n, sc in enumerate(scans):
        fi_s, w_s = sample_surface(sc.vertices, sc.faces, cfg.scan_samples, rng)
        scan_pts = (sc.vertices[sc.faces[fi_s]] * w_s[..., None]).sum(1)
        fi_m, w_m = sample_surface(current[n], faces_np, cfg.model_samples, rng)
        model_pts = (current[n][faces_np[fi_m]] * w_m[..., None]).sum(1)
        im, js = mutual_nearest_neighbours(model_pts, scan_pts)
        nrm = None
        if scan_normals is not None:
            nrm = (scan_normals[n][sc.faces[fi_s[js]]] * w_s[js][..., None]).sum(1)
            nrm = torch.as_tensor(nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12), dtype=dtype)
        pairs.append((
            faces[torch.as_tensor(fi_m[im])],
            torch.as_tensor(w_m[im], dtype=dtype),
            torch.as_tensor(scan_pts[js], dtype=dtype),
            torch.tensor(float(len(im))),
            nrm,
        ))
    return pairs


def pair_term(residual: torch.Tensor, normals: torch.Tensor | None, tangent_weight: float = 1.0) -> torch.Tensor:
    """Mean squared MNN residual, its along-surface part weighted (Eq. 5.15's first term at 1).

    Args:
        residual: (P, 3) model sample minus scan sample, metres.
        normals: (P, 3) unit scan normals at the scan samples (needed when ``tangent_weight < 1``).
        tangent_weight: weight of ``|r|^2 - (r . n)^2``; 1 = point-to-point, 0 = point-to-plane.

    Returns:
        () mean over the pairs, m^2.
    """
    sq = residual.square().sum(-1)
    if tangent_weight == 1.0:
        return sq.mean()
    if normals is None:
        raise ValueError("a tangent weight below 1 needs the scan normals")
    rn2 = (residual * normals).sum(-1).square()
    return (rn2 + tangent_weight * (sq - rn2)).mean()


def _landmark_targets(scans, dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Located landmarks (B, L, 3) with NaN rows zeroed, their mask (B, L) and count (B,)."""
    x_lm = torch.as_tensor(np.stack([s.landmarks for s in scans]), dtype=dtype)  # (B, L, 3)
    lm_mask = torch.isfinite(x_lm).all(-1)
    x_lm = torch.where(lm_mask[..., None], x_lm, torch.zeros_like(x_lm))
    return x_lm, lm_mask, lm_mask.sum(1).clamp(min=1).to(dtype)


def fit_surface(
    model,
    scans: Sequence[ScanData],
    stage1: Stage1,
    selection: LandmarkSelection,
    config: RegisterConfig | None = None,
) -> Stage1:
    """Engineering addition (not in the thesis): fit the initial model to the scan *surface*.

    Between Eq. 5.13 and Eq. 5.14: the skeleton (angles, bone scales, rigid motion) and the
    initial model's shape coefficients (Eq. 8) are refined on the data term of Eq. 5.15 (mean
    squared MNN distance, Eq. 5.16, plus the landmark term) with the same priors as stage 1, in
    ``surface_rounds`` ICP rounds: fresh samples and MNN pairs, then ``surface_iterations`` L-BFGS
    iterations with the pairs fixed (model samples as faces + barycentrics, so they move with the
    parameters). A parametric model only moves along its shape space, so it cannot slide vertices
    along the surface the way free displacements do: it puts the soft tissue (belly, chest, back,
    hips) where the landmarks alone cannot, and stage 2 then only has to close a small gap.

    Args:
        model: a :class:`blsm.BLSM`. scans: B scans. stage1: the landmark fit of the same scans.
        selection: template landmarks A_lm. config: settings (defaults if None).

    Returns:
        A refined :class:`Stage1` (detached); ``landmark_error`` is recomputed.
    """
    cfg = config or RegisterConfig()
    if cfg.surface_rounds == 0 or cfg.surface_iterations == 0:
        return stage1
    dtype = model.template.dtype
    bsz = len(scans)
    rng = np.random.default_rng(cfg.seed + 1)
    use_shape = cfg.shape_init and model.num_shape_coeffs > 0
    beta0 = stage1.shape if stage1.shape is not None else torch.zeros(bsz, model.num_shape_coeffs, dtype=dtype)
    beta = beta0.clone().requires_grad_(use_shape)
    x = unconstrained_from_angles(stage1.angles, model.dof_limits, eps=1e-4).clone().requires_grad_(True)
    log_b = stage1.bone_scales.log().clone().requires_grad_(True)
    go = stage1.global_orient.clone().requires_grad_(True)
    tr = stage1.transl.clone().requires_grad_(True)
    x_lm, lm_mask, lm_count = _landmark_targets(scans, dtype)
    faces = model.faces

    def mesh() -> torch.Tensor:
        tmpl = model.template + model.shape_decoder(beta) if use_shape else model.template
        return pose(model, tmpl, bone_scales=log_b.exp(), pose=x, global_orient=go, transl=tr).vertices

    params = [x, log_b, go, tr] + ([beta] if use_shape else [])
    for _ in range(cfg.surface_rounds):
        with torch.no_grad():
            cur = mesh().numpy()
        pairs = [p[:3] for p in _mnn_pairs(scans, cur, faces, cfg, rng, dtype)]
        opt = torch.optim.LBFGS(params, lr=1.0, max_iter=cfg.surface_iterations, line_search_fn="strong_wolfe",
                                tolerance_grad=1e-12, tolerance_change=1e-15, history_size=20)

        def closure():
            opt.zero_grad()
            v = mesh()
            e_mnn = torch.stack([((v[n, f] * w[..., None]).sum(1) - t).square().sum(-1).mean()
                                 for n, (f, w, t) in enumerate(pairs)])
            e_lm = ((selection.select(v) - x_lm).square().sum(-1) * lm_mask).sum(1) / lm_count
            loss = (cfg.lambda_mnn * e_mnn + cfg.lambda_lm * e_lm).sum()
            loss = loss + cfg.angle_prior * pose_angles(model, x).square().mean(1).sum()
            loss = loss + cfg.scale_prior * (log_b - model.bone_mean.log()).square().mean(1).sum()
            if use_shape:
                loss = loss + cfg.shape_prior * beta.square().mean(1).sum()
            loss.backward()
            return loss

        opt.step(closure)
    with torch.no_grad():
        v = mesh()
        rms = (((selection.select(v) - x_lm).square().sum(-1) * lm_mask).sum(1) / lm_count).sqrt()
        offs = model.shape_decoder(beta) if use_shape else torch.zeros(bsz, *model.template.shape, dtype=dtype)
        return Stage1(log_b.exp().detach(), pose_angles(model, x).detach(), go.detach(), tr.detach(), rms,
                      beta.detach(), offs.detach())


def fit_stage1(model, scans: Sequence[ScanData], selection: LandmarkSelection,
               config: RegisterConfig) -> tuple[Stage1, Stage1]:
    """Stage 1 of B scans: :func:`fit_landmarks` (Eq. 5.13), then :func:`fit_surface`.

    Returns:
        (the landmark fit, the surface refit that stage 2 starts from).
    """
    lms = torch.as_tensor(np.stack([d.landmarks for d in scans]), dtype=model.template.dtype)
    st1 = fit_landmarks(model, lms, selection, config)
    return st1, fit_surface(model, scans, st1, selection, config)


# ------------------------------------------------------------------------------------------------
# Stage 2: free-form refinement (Eqs. 5.14-5.25)


@dataclass
class ScanData:
    """What :func:`refine` needs of one scan (numpy, metres, world frame).

    Attributes:
        vertices: (N, 3). faces: (F, 3). landmarks: (L, 3) in the selection's order, NaN = missing.
    """

    vertices: np.ndarray
    faces: np.ndarray
    landmarks: np.ndarray


class Stage2Energy:
    """The objective of Eq. 5.14 for B scans, with the stage-1 skeleton held fixed (Eqs. 5.15-5.25).

    ``S^ = S^_T + A V_D`` (LBS is linear in the template for fixed transforms, Eq. 12), where S^_T is
    the stage-1 mesh and A (B, V, 3, 3) the blended rotation-scale of each vertex. Separate from
    :func:`refine` so that the energy can be evaluated at any mesh, e.g. at known correspondences.

    Args:
        model: a :class:`blsm.BLSM`. scans: B :class:`ScanData`. stage1: their stage-1 fit.
        selection: template landmarks A_lm. config: settings.
    """

    def __init__(self, model, scans: Sequence[ScanData], stage1: Stage1, selection: LandmarkSelection,
                 config: RegisterConfig) -> None:
        self.cfg, self.scans, self.selection = config, scans, selection
        self.dtype = model.template.dtype
        with torch.no_grad():
            tmpl = model.template if stage1.shape_offsets is None else model.template + stage1.shape_offsets
            posed = pose(model, tmpl, bone_scales=stage1.bone_scales, angles=stage1.angles,
                         global_orient=stage1.global_orient, transl=stage1.transl)
            self.s_t = posed.vertices  # (B, V, 3) S^_T
            self.lin = torch.einsum("vj,bjrc->bvrc", model.weights, posed.transforms[..., :3])  # (B, V, 3, 3)
        self.faces = model.faces
        self.edges = mesh_edges(self.faces)
        hand_ids = [model.bone_names.index(n) for n in HAND_BONES]
        is_hand = torch.isin(model.vertex_bones, torch.tensor(hand_ids))
        self.hand_edges = self.edges[is_hand[self.edges[:, 0]] & is_hand[self.edges[:, 1]]]
        self.x_lm, self.lm_mask, self.lm_count = _landmark_targets(scans, self.dtype)
        # Scan vertex normals, once, for the point-to-plane part of the data term.
        self.scan_normals = ([vertex_normals(sc.vertices, sc.faces) for sc in scans]
                             if config.mnn_tangent_weight < 1 else None)

    def mesh(self, v_d: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) T-pose displacements V_D -> (B, V, 3) posed S^."""
        return self.s_t + torch.einsum("bvrc,bvc->bvr", self.lin, v_d)

    def displacement(self, s_hat: torch.Tensor) -> torch.Tensor:
        """The V_D (B, V, 3) whose mesh is ``s_hat`` (inverse of :meth:`mesh`)."""
        return torch.linalg.solve(self.lin, (s_hat.to(self.dtype) - self.s_t)[..., None])[..., 0]

    def pairs(self, s_hat: torch.Tensor, rng: np.random.Generator) -> list[Any]:
        """Fresh samples and MNN pairs (Eq. 5.16) on the meshes ``s_hat`` (B, V, 3), detached."""
        return _mnn_pairs(self.scans, s_hat.detach().numpy(), self.faces, self.cfg, rng, self.dtype,
                          self.scan_normals)

    def terms(self, s_hat: torch.Tensor, pairs: list[Any]) -> dict[str, torch.Tensor]:
        """Unweighted terms, each (B,): mnn, lm (Eq. 5.15), smooth (5.21), ev, el (5.22), rigid
        (5.25), normalised as ``cfg.normalisation`` says; and ``pairs``, the MNN pair counts."""
        cfg = self.cfg
        e_mnn = torch.stack([
            pair_term((s_hat[n, f] * w[..., None]).sum(1) - tgt, nrm, cfg.mnn_tangent_weight) if len(tgt) else s_hat.new_zeros(())
            for n, (f, w, tgt, _, nrm) in enumerate(pairs)
        ])  # (B,) Eq. 5.15 first term, mean over MNN pairs
        e_lm = ((self.selection.select(s_hat) - self.x_lm).square().sum(-1) * self.lm_mask).sum(1) / self.lm_count
        e_smooth = uniform_laplacian(s_hat, self.edges).norm(dim=-1).mean(1)  # Eq. 5.21
        ev, el = edge_terms(s_hat, self.s_t, self.edges)  # Eq. 5.22
        evh, elh = edge_terms(s_hat, self.s_t, self.hand_edges)  # Eq. 5.25
        counts = torch.stack([p[3] for p in pairs])
        if cfg.normalisation == "sum":
            nv = float(s_hat.shape[1])
            ne, nh = self.edges.shape[0], self.hand_edges.shape[0]
            e_mnn = e_mnn * counts.to(self.dtype) / nv
            e_lm = e_lm * self.lm_count / nv
            ev, el, evh, elh = ev * ne / nv, el * ne / nv, evh * nh / nv, elh * nh / nv
        return {"mnn": e_mnn, "lm": e_lm, "smooth": e_smooth, "ev": ev, "el": el, "rigid": evh + elh, "pairs": counts}

    def weighted(self, terms: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Each energy term of :meth:`terms` times its lambda (``pairs`` left out)."""
        cfg = self.cfg
        lam = {"mnn": cfg.lambda_mnn, "lm": cfg.lambda_lm, "smooth": cfg.lambda_smoothness,
               "ev": cfg.lambda_ev, "el": cfg.lambda_el, "rigid": cfg.lambda_rigid}
        return {k: w * terms[k] for k, w in lam.items()}

    def total(self, terms: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B,) the weighted sum of :meth:`terms` (Eq. 5.14)."""
        return torch.stack(list(self.weighted(terms).values())).sum(0)


def refine(
    model,
    scans: Sequence[ScanData],
    stage1: Stage1,
    selection: LandmarkSelection,
    config: RegisterConfig | None = None,
    log: Any = None,
    init: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, list[dict[str, float]]]:
    """Eqs. 5.14-5.25: per-vertex displacements V_D with the stage-1 skeleton fixed.

    Args:
        model: a :class:`blsm.BLSM`.
        scans: B scans.
        stage1: the landmark fit of the same B scans.
        selection: template landmarks A_lm.
        config: settings (defaults if None).
        log: a callable taking a progress string, or None.
        init: (B, V, 3) initial V_D (T-pose frame, on top of the stage-1 shape offsets), or None
            for zeros; e.g. to start at known correspondences and see where the energy moves them.

    Returns:
        V_D (B, V, 3) in the T-pose frame, S^ (B, V, 3) posed, and per-scan final loss terms.
    """
    cfg = config or RegisterConfig()
    bsz = len(scans)
    rng = np.random.default_rng(cfg.seed)
    energy = Stage2Energy(model, scans, stage1, selection, cfg)
    v_d = torch.zeros_like(energy.s_t) if init is None else init.to(energy.s_t.dtype).clone()
    v_d.requires_grad_(True)
    opt = torch.optim.Adam([v_d], lr=cfg.lr)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=cfg.lr_decay, patience=cfg.plateau_patience,
                                                       threshold=1e-3)
    pairs: list[Any] = []
    terms: dict[str, torch.Tensor] = {}
    for it in range(cfg.iterations):
        s_hat = energy.mesh(v_d)  # (B, V, 3)
        if it % cfg.mnn_refresh == 0:
            pairs = energy.pairs(s_hat.detach(), rng)
        terms = energy.terms(s_hat, pairs)
        loss = energy.total(terms).sum()
        if not torch.isfinite(loss):
            raise RuntimeError(f"registration loss became {float(loss)} at iteration {it}")
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step(float(loss.detach()))
        terms = {k: v.detach() for k, v in terms.items()}
        if log is not None and (it % 50 == 0 or it == cfg.iterations - 1):
            log(f"  stage 2 it {it:4d}: loss {float(loss.detach()):.3e}, mnn rms "
                f"{float(terms['mnn'].sqrt().mean()) * 1000:.2f} mm, lm rms {float(terms['lm'].sqrt().mean()) * 1000:.2f} mm, "
                f"lr {opt.param_groups[0]['lr']:.2e}")
    with torch.no_grad():
        s_hat = energy.mesh(v_d)
        v_out = v_d.detach() if stage1.shape_offsets is None else v_d.detach() + stage1.shape_offsets
    stats = [{k: float(v[n]) for k, v in terms.items()} for n in range(bsz)]
    return v_out, s_hat, stats


# ------------------------------------------------------------------------------------------------
# Driver


def default_selection(model) -> LandmarkSelection:
    """The packaged landmark set (``blsm.learn.scans.template_landmarks``)."""
    try:
        from blsm.learn.scans import template_landmarks
    except ImportError as exc:
        raise ValueError("no landmark selection given and blsm.learn.scans is not available") from exc
    names, index, bary = template_landmarks(model)  # (L,), (L, 3) vertices, (L, 3) weights
    return LandmarkSelection(list(names), torch.as_tensor(index).long(), torch.as_tensor(bary).float())


def _scan_data(scan: Any, selection: LandmarkSelection, where: str) -> ScanData:
    """Validate a scan (Scan-like object) and order its landmarks as the selection's."""
    v = np.asarray(scan.vertices, dtype=np.float64)
    f = np.asarray(scan.faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"{where}: scan has no vertices (shape {v.shape})")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"{where}: scan has no triangles (faces shape {f.shape})")
    if not np.isfinite(v).all():
        raise ValueError(f"{where}: scan vertices contain NaN or inf")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"{where}: scan faces index outside [0, {len(v)})")
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    if (counts > 2).any():
        raise ValueError(f"{where}: scan is non-manifold ({int((counts > 2).sum())} edges shared by more than 2 faces)")
    names = [str(n) for n in (scan.landmark_names if scan.landmark_names is not None else [])]
    lms = np.asarray(scan.landmarks if scan.landmarks is not None else np.zeros((0, 3)), dtype=np.float64)
    if lms.shape != (len(names), 3):
        raise ValueError(f"{where}: landmarks must be ({len(names)}, 3), got {lms.shape}")
    lookup = {n: i for i, n in enumerate(names)}
    out = np.full((len(selection), 3), np.nan)
    for k, n in enumerate(selection.names):
        if n in lookup:
            out[k] = lms[lookup[n]]
    located = int(np.isfinite(out).all(1).sum())
    if located < 6:
        raise ValueError(f"{where}: only {located} landmarks located that the template knows (need >= 6)")
    return ScanData(v, f.astype(np.int64), out)


def register(
    model,
    scans: Sequence[Any],
    config: RegisterConfig | None = None,
    landmark_index: Any = None,
    landmark_names: Sequence[str] | None = None,
    selection: LandmarkSelection | None = None,
    progress: bool = True,
) -> list[Registration]:
    """Register B scans to the BLSM template (Eq. 5.13, then Eqs. 5.14-5.25), batched.

    Args:
        model: a :class:`blsm.BLSM`.
        scans: objects with ``vertices`` (N, 3), ``faces`` (F, 3), ``landmark_names`` (L,),
            ``landmarks`` (L, 3) (NaN rows = not located) and ``meta`` (dict), e.g.
            ``blsm.learn.scans.Scan``.
        config: settings (defaults if None).
        landmark_index: (L,) template vertex indices of the landmarks, with ``landmark_names``;
            or ``selection`` directly; neither means ``blsm.learn.scans.template_landmarks``.
        progress: print progress lines on stderr.

    Returns:
        One :class:`Registration` per scan.
    """
    cfg = config or RegisterConfig()
    if selection is None:
        if landmark_index is not None:
            if landmark_names is None:
                raise ValueError("landmark_index needs landmark_names")
            selection = LandmarkSelection.from_index(landmark_names, landmark_index)
        else:
            selection = default_selection(model)
    log = (lambda s: print(s, file=sys.stderr, flush=True)) if progress else None
    data = []
    for n, s in enumerate(scans):
        meta = getattr(s, "meta", None) or {}
        data.append(_scan_data(s, selection, str(meta.get("id", f"scan {n}"))))
    t0 = time.perf_counter()
    st1_lm, st1 = fit_stage1(model, data, selection, cfg)
    st1_lm_rms = st1_lm.landmark_error
    t1 = time.perf_counter()
    if log:
        log(f"stage 1: {len(data)} scans, landmark rms {[round(float(e) * 1000, 2) for e in st1.landmark_error]} mm, "
            f"{t1 - t0:.1f} s")
    v_d, s_hat, stats = refine(model, data, st1, selection, cfg, log)
    t2 = time.perf_counter()
    if log:
        log(f"stage 2: {cfg.iterations} iterations, {t2 - t1:.1f} s")
    out = []
    for n, s in enumerate(scans):
        meta = dict(getattr(s, "meta", None) or {})
        info = {
            "scan": meta.get("id"), "subject": meta.get("subject"), "pose": meta.get("pose"),
            "split": meta.get("split"),
            "stage1_landmark_rms_mm": float(st1_lm_rms[n]) * 1000,
            "surface_fit_landmark_rms_mm": float(st1.landmark_error[n]) * 1000,
            "landmark_rms_mm": math.sqrt(stats[n]["lm"]) * 1000,
            "mnn_rms_mm": math.sqrt(stats[n]["mnn"]) * 1000,
            "mnn_pairs": int(stats[n]["pairs"]),
            "stage1_iterations": cfg.stage1_iterations, "iterations": cfg.iterations,
            "seconds": (t2 - t0) / len(scans),
            "config": dataclasses.asdict(cfg),
        }
        gt = getattr(s, "gt_points", None)
        if gt is not None and np.asarray(gt).shape == tuple(s_hat[n].shape):
            reg0 = Registration(st1_vertices(model, st1, n), *([np.zeros(1)] * 5))
            m0, x0 = correspondence_error(reg0, gt)
            m1, x1 = correspondence_error(Registration(s_hat[n].numpy(), *([np.zeros(1)] * 5)), gt)
            info.update(stage1_error_mean_mm=m0, stage1_error_max_mm=x0, error_mean_mm=m1, error_max_mm=x1)
        out.append(Registration(
            vertices=s_hat[n].numpy().astype(np.float32),
            bone_scales=st1.bone_scales[n].numpy().astype(np.float32),
            angles=st1.angles[n].numpy().astype(np.float32),
            global_orient=st1.global_orient[n].numpy().astype(np.float32),
            transl=st1.transl[n].numpy().astype(np.float32),
            displacement=v_d[n].numpy().astype(np.float32),
            meta=info,
        ))
    return out


def st1_vertices(model, st1: Stage1, n: int) -> np.ndarray:
    """(V, 3) the stage-1 mesh S^_T of scan ``n`` (metres)."""
    with torch.no_grad():
        tmpl = model.template if st1.shape_offsets is None else model.template + st1.shape_offsets[n]
        return pose(model, tmpl, bone_scales=st1.bone_scales[n:n + 1], angles=st1.angles[n:n + 1],
                    global_orient=st1.global_orient[n:n + 1], transl=st1.transl[n:n + 1]).vertices[0].numpy()


# ------------------------------------------------------------------------------------------------
# Landmark definitions and scan files for the command line


def read_landmark_definitions(path: str | Path, model) -> LandmarkSelection:
    """Read template landmarks from YAML: ``name: {vertex: i}`` or ``name: {face: f, bary: [a, b, c]}``.

    A top-level ``landmarks:`` mapping is also accepted.
    """
    path = Path(path)
    data = read_yaml(path, "landmark definitions")
    if isinstance(data, dict) and isinstance(data.get("landmarks"), dict):
        data = data["landmarks"]
    if not isinstance(data, dict) or not data:
        raise ValueError(f"{path}: expected a mapping name -> {{vertex: i}} or {{face: f, bary: [a, b, c]}}")
    names, verts, bary = [], [], []
    nv, nf = model.num_vertices, int(model.faces.shape[0])
    for name, spec in data.items():
        if not isinstance(spec, dict):
            raise ValueError(f"{path}: {name}: expected {{vertex: i}} or {{face: f, bary: [a, b, c]}}")
        if "vertex" in spec and isinstance(spec["vertex"], int) and 0 <= spec["vertex"] < nv:
            verts.append([spec["vertex"]] * 3)
            bary.append([1.0, 0.0, 0.0])
        elif "face" in spec and isinstance(spec["face"], int) and 0 <= spec["face"] < nf \
                and isinstance(spec.get("bary"), list) and len(spec["bary"]) == 3:
            verts.append(model.faces[spec["face"]].tolist())
            bary.append([float(b) for b in spec["bary"]])
        else:
            raise ValueError(f"{path}: {name}: bad landmark {spec!r} (vertex in [0, {nv}) or face in [0, {nf}) + bary)")
        names.append(str(name))
    return LandmarkSelection(names, torch.tensor(verts, dtype=torch.long), torch.tensor(bary, dtype=torch.float32))


def main(argv: list[str] | None = None) -> int:
    """``blsm register SCAN [SCAN ...] --out DIR [--landmarks FILE] [--config YAML] [--model FILE]``.

    A scan is a ``blsm-scan`` ``.npz`` or an OBJ / PLY / GLB mesh whose located landmarks are in
    ``<stem>.landmarks.json`` beside it, or in ``--landmarks FILE`` (one scan only).
    """
    parser = argparse.ArgumentParser(
        prog="blsm register",
        description="Register the BLSM template to scans (thesis Sec. 5.4.1): landmark fit, then "
                    "free-form refinement; writes one blsm-registration .npz per scan.",
    )
    parser.add_argument("scans", nargs="+", type=Path, help="scan files (blsm-scan .npz, or OBJ/PLY/GLB)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--landmarks", type=Path, help="the scan's located landmarks, JSON {name: [x, y, z]} "
                        "(default: <scan stem>.landmarks.json beside a mesh; inside a .npz scan)")
    parser.add_argument("--landmark-definitions", type=Path, help="template landmark definitions YAML "
                        "(default: blsm/data/landmarks.yaml via blsm.learn.scans)")
    parser.add_argument("--config", type=Path, help="RegisterConfig YAML (default: configs/blsm/register.yaml "
                        "when present, else the thesis' values)")
    parser.add_argument("--model", type=Path, help="BLSM model file (default: the packaged one)")
    parser.add_argument("--batch", type=int, default=4, help="scans registered together (default 4)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing registration files")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    try:
        import blsm
        from blsm.learn.scans import load_scan

        model = blsm.load(args.model)
        if args.config is not None:
            cfg = load_config(args.config)
        else:
            cfg = load_config(DEFAULT_CONFIG) if DEFAULT_CONFIG.is_file() else RegisterConfig()
        selection = (
            read_landmark_definitions(args.landmark_definitions, model)
            if args.landmark_definitions else default_selection(model)
        )
        if args.landmarks is not None and len(args.scans) != 1:
            raise ValueError(f"{args.landmarks}: --landmarks names the landmarks of one scan, got {len(args.scans)} scans")
        if args.batch < 1:
            raise ValueError(f"--batch must be >= 1, got {args.batch}")
        jobs = []
        for p in args.scans:
            target = args.out / f"{p.stem}.npz"
            if target.exists() and not args.overwrite:
                raise ValueError(f"{target}: exists (use --overwrite to replace it)")
            scan = load_scan(p, landmarks=args.landmarks, require_landmarks=True)
            meta = dict(getattr(scan, "meta", None) or {})
            meta.setdefault("id", p.stem)
            scan.meta = meta
            _scan_data(scan, selection, str(p))  # fail fast, naming the file
            jobs.append((scan, target))
        for i in range(0, len(jobs), args.batch):
            chunk = jobs[i:i + args.batch]
            regs = register(model, [s for s, _ in chunk], cfg, selection=selection)
            for reg, (_, target) in zip(regs, chunk):
                save_registration(reg, target)
                print(f"wrote {target}", file=sys.stderr)
    except ValueError as exc:
        print(f"blsm register: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
