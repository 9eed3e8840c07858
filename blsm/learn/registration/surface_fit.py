"""Stages 1b and 2 of the scan registration: fitting the template to the scan surface.

1. :func:`fit_surface` (engineering addition, not in the thesis): the skeleton (angles, bone
   scales, rigid motion) and the initial model's shape coefficients are refined on the scan
   surface (mutual nearest neighbours plus landmarks), in ICP rounds with L-BFGS.
2. :func:`refine` (thesis Eqs. 5.14-5.25): free per-vertex displacements V_D in the T-pose frame,
   ``S^ = LBS(V_T + V_D, T(s, theta))`` with the stage-1 skeleton held fixed, minimising
   ``E_data + E_smoothness + E_reg + E_rigid`` (:class:`Stage2Energy`) with Adam.

Normalisation (checked for metre units): every term is a *mean* over its elements (MNN pairs,
located landmarks, vertices, edges), as PyTorch3D's losses (which the thesis used) are. The counts
are of the same order (about 7k vertices, 21k edges, 5k-10k MNN pairs), so the thesis' relative
weights keep their meaning, and the loss of one scan does not depend on how many scans share a
batch. Note that in metres the edge-length term of Eq. 5.24 (squared lengths, about 1e-4 m^2) is
tiny; it is kept as written. For the same reason lambda_EV is 3.0, not the thesis' 0.003 (see
:class:`blsm.learn.registration.register_config.RegisterConfig`).

Mutual nearest neighbours (Eq. 5.16) are found with ``scipy.spatial.cKDTree`` on the CPU on fresh
surface samples every ``mnn_refresh`` iterations; between refreshes the samples (faces and
barycentric coordinates on S^) and the pairs are kept, while the model samples move with V_D, so
the gradients still reach the vertices.

Units and conventions: metres, radians, Y up, the body faces +Z at rest, +X is the body's left.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from blsm.joint_limits import unconstrained_from_angles
from blsm.learn.posing import pose
from blsm.learn.registration.landmark_fit import LandmarkSelection, Stage1, lbfgs, pose_angles
from blsm.learn.registration.register_config import RegisterConfig
from blsm.mesh import mesh_edges, uniform_laplacian, vertex_normals

HAND_BONES: tuple[str, ...] = ("wrist_l", "wrist_r")


@dataclass
class ScanData:
    """What :func:`refine` needs of one scan (numpy, metres, world frame).

    Attributes:
        vertices: (N, 3). faces: (F, 3). landmarks: (L, 3) in the selection's order, NaN = missing.
    """

    vertices: np.ndarray
    faces: np.ndarray
    landmarks: np.ndarray


# ------------------------------------------------------------------------------------------------
# Surface samples, pairs and energy terms (pure functions)


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


# ------------------------------------------------------------------------------------------------
# The surface fit of the skeleton and shape (engineering addition)


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

    def mesh() -> torch.Tensor:
        tmpl = model.template + model.shape_decoder(beta) if use_shape else model.template
        return pose(model, tmpl, bone_scales=log_b.exp(), pose=x, global_orient=go, transl=tr).vertices

    def loss(pairs: list[Any]) -> torch.Tensor:
        v = mesh()
        e_mnn = torch.stack([((v[n, f] * w[..., None]).sum(1) - t).square().sum(-1).mean()
                             for n, (f, w, t) in enumerate(pairs)])
        e_lm = ((selection.select(v) - x_lm).square().sum(-1) * lm_mask).sum(1) / lm_count
        out = (cfg.lambda_mnn * e_mnn + cfg.lambda_lm * e_lm).sum()
        out = out + cfg.angle_prior * pose_angles(model, x).square().mean(1).sum()
        out = out + cfg.scale_prior * (log_b - model.bone_mean.log()).square().mean(1).sum()
        if use_shape:
            out = out + cfg.shape_prior * beta.square().mean(1).sum()
        return out

    params = [x, log_b, go, tr] + ([beta] if use_shape else [])
    for _ in range(cfg.surface_rounds):
        with torch.no_grad():
            cur = mesh().numpy()
        pairs = [p[:3] for p in _mnn_pairs(scans, cur, model.faces, cfg, rng, dtype)]
        lbfgs(params, cfg.surface_iterations, lambda pairs=pairs: loss(pairs))
    with torch.no_grad():
        v = mesh()
        rms = (((selection.select(v) - x_lm).square().sum(-1) * lm_mask).sum(1) / lm_count).sqrt()
        offs = model.shape_decoder(beta) if use_shape else torch.zeros(bsz, *model.template.shape, dtype=dtype)
        return Stage1(log_b.exp().detach(), pose_angles(model, x).detach(), go.detach(), tr.detach(), rms,
                      beta.detach(), offs.detach())


# ------------------------------------------------------------------------------------------------
# Free-form refinement (Eqs. 5.14-5.25)


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
