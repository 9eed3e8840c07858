"""Registration from 3D keypoints (thesis Sec. 6.3, Eqs. 6.4-6.6), over frames of one subject.

1. :func:`fit_keypoints` (Eq. 6.4): one set of bone coefficients c_b per subject, shared over its
   frames, and a pose theta_t (atom angles through the unconstrained x of Eq. 5.6, global
   orientation, translation) per frame minimise

       sum_t cf_t rho(||A_kp BLSM(c_b; theta_t) - L_t||^2) + S(theta) + priors,

   with A_kp a :class:`KeypointSet` (the model's keypoints, some joints and some surface points, or
   the scan landmarks of :mod:`blsm.learn.registration.landmark_fit`), per-keypoint confidences cf and the
   Geman-McClure function rho (scale ``robust_scale``), so that a wrong detection (a left/right swap)
   does not pull the body. S is the temporal smoothing of a sequence (:func:`smoothing`): squared
   accelerations of the posed joints (m/s^2) and of the angles (rad/s^2), and squared velocities of
   the joints (m/s), finite differences over the frames' times (:func:`frame_times`), so that frames
   far apart in time are smoothed less; zero for a single frame. Initialisation: Kabsch of the trunk
   keypoints onto the rest model's, and the same turned by pi about the body's vertical axis (facing
   ambiguity), each followed by ``trial_iterations`` L-BFGS steps; the better start per frame is kept.
2. :func:`fit_shape` (Eqs. 6.5-6.6): the shape coefficients c_s (shared per subject) jointly with c_b
   and theta_t on mutual nearest neighbours (Eq. 5.16, :func:`blsm.learn.registration.surface_fit.mutual_nearest_neighbours`)
   between the posed model and ``scan_samples`` points of each scan, plus ``lambda_kp`` times the
   keypoint term and S, in ICP rounds. Scan samples farther than ``crop_distance`` from the current
   body are dropped (stools, floor markers), and triangles larger than ``max_triangle_area`` are not
   sampled (big triangles bridging holes, Sec. 6.3.4).

The person template is ``V_T + c_b P_bc + V_s(c_s)`` (Eqs. 1, 7, 8) and the bone scales
``b = b_mean + c_b P_b`` (Eq. 4); the result converts to a :class:`blsm.learn.registration.landmark_fit.Stage1`
(per-frame bone scales and the template offsets) so that the free-form stage
(:func:`blsm.learn.registration.surface_fit.refine`, Eqs. 5.14-5.25) runs on it unchanged.

Units and conventions: metres, radians, Y up, the body faces +Z at rest, +X is the body's left.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from blsm.joint_limits import unconstrained_from_angles
from blsm.kinematics import bone_scales
from blsm.learn.posing import pose
from blsm.learn.registration.landmark_fit import LandmarkSelection, Stage1, lbfgs, pose_angles
from blsm.learn.registration.surface_fit import mutual_nearest_neighbours, sample_surface
from blsm.learn.registration.temporal import (
    REFERENCE_FPS,
    check_times,
    frame_times,
    outlier_frames,
    smoothing,
)

__all__ = [
    "KeypointFit",
    "KeypointFitConfig",
    "KeypointSet",
    "fit_keypoints",
    "fit_shape",
    "frame_times",
    "geman_mcclure",
    "load_keypoint_config",
    "outlier_frames",
    "smoothing",
]

# Keypoints whose positions fix the global rigid motion (joints and their COCO twins).
TRUNK_KEYPOINTS: tuple[str, ...] = (
    "pelvis", "spine_01", "spine_02", "spine_03", "neck", "clavicle_l", "clavicle_r", "shoulder_l",
    "shoulder_r", "hip_l", "hip_r", "left_shoulder", "right_shoulder", "left_hip", "right_hip",
)  # fmt: skip


# Geman-McClure scales (metres) of the facing trials and the first rounds of Eq. 6.4, before
# ``robust_scale``.
ANNEAL: tuple[float, ...] = (0.3, 0.1)

@dataclass
class KeypointFitConfig:
    """Settings of :func:`fit_keypoints` and :func:`fit_shape`.

    Attributes:
        rigid_iterations: L-BFGS iterations on the global rigid motion only, first.
        trial_iterations: L-BFGS iterations from each of the two facing starts (0: Kabsch only).
        iterations: L-BFGS iterations of Eq. 6.4.
        robust_scale: Geman-McClure scale sigma, metres: a keypoint ``sigma`` off costs half its
            squared distance, a far one at most sigma^2.
        angle_prior: weight (m^2 per rad^2) of mean(theta^2) (as ``RegisterConfig.angle_prior``).
        bone_prior: weight (m^2) of mean(c_b^2) (coefficients in standard deviations).
        shape_prior: weight (m^2) of mean(c_s^2).
        smooth_accel: weight (s^4) of the mean squared acceleration of the posed joints, (m/s^2)^2
            (S of Eq. 6.4, :func:`smoothing`). 0.1 / 15^4: at 15 fps the 0.1 per squared second
            difference (metres) it was set at until 2026-12-06 (weights on per-frame differences,
            whatever the frames' spacing, over-smoothed frames 4 clip frames apart: issue 53). Small:
            the robust keypoint term is bounded (sigma^2 per keypoint) and the smoothing is not, so at
            10 times this (1.0 per squared second difference) fast frames of a 15 fps walk drifted 5-8 cm
            off their keypoints.
        smooth_velocity: weight (s^2) of the mean squared velocity of the posed joints, (m/s)^2 (0: it
            would slow down any motion).
        smooth_angle_accel: weight (m^2 s^4 per rad^2) of the mean squared angular acceleration,
            (rad/s^2)^2 (the joints do not see twists); 1e-4 / 15^4, as ``smooth_accel``.
        fps: frame rate of a sequence's frames as given, frames per second: each next frame 1 / fps
            seconds later (``blsm register --fps``). 0: the scans' own times where they carry them
            (:func:`frame_times`), else ``REFERENCE_FPS`` (15).
        surface_rounds, surface_iterations: ICP rounds and L-BFGS iterations per round of Eq. 6.5.
            96 x 60 (6 x 15 until 2026-11-28, far from converged; 48 x 60 until 2026-12-01): chosen
            on a validation population of stand-in scans (docs/markerless.md, "Eq. 6.5 run to
            convergence").
        stage2_iterations: iterations of the free-form stage after Eq. 6.5
            (:func:`blsm.learn.registration.surface_fit.refine`) in :func:`blsm.learn.registration.register.register_keypoints`;
            0 keeps ``RegisterConfig.iterations`` (150, the landmark registration's).
        hand_search_round: after this many rounds of Eq. 6.5, search the hands again on the finer
            grid around the fitted angles (:func:`blsm.learn.registration.end_search.search_hands` with
            ``around=True``; the first search runs on the Eq. 6.4 body, mean shape), then run the
            remaining rounds; 0: no second search. 48 (with 96 rounds) since 2026-12-01, chosen on
            the validation population.
        foot_search: at that round, search the ankles around the fit too
            (:func:`blsm.learn.registration.end_search.search_feet`); on since 2026-12-01 (validation population).
        lambda_kp: weight of the keypoint term in Eq. 6.5 (thesis: 0.1).
        scan_samples: points sampled on each scan per round (thesis: 10k). model_samples: on the model.
        crop_distance: scan samples farther than this from the current body, and MNN pairs longer
            than this, are dropped, metres (half of it after the first round).
        max_triangle_area: scan triangles larger than this are not sampled, m^2 (0: all).
        seed: random seed of the surface sampling.
    """

    rigid_iterations: int = 30
    trial_iterations: int = 40
    iterations: int = 240
    robust_scale: float = 0.04
    angle_prior: float = 1e-5
    bone_prior: float = 1e-5
    shape_prior: float = 1e-5
    smooth_accel: float = 0.1 / REFERENCE_FPS**4
    smooth_velocity: float = 0.0
    smooth_angle_accel: float = 1e-4 / REFERENCE_FPS**4
    fps: float = 0.0
    surface_rounds: int = 96
    surface_iterations: int = 60
    lambda_kp: float = 0.1
    scan_samples: int = 10_000
    model_samples: int = 8_000
    crop_distance: float = 0.1
    max_triangle_area: float = 0.0
    stage2_iterations: int = 300
    hand_search_round: int = 48
    foot_search: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        for k, v in vars(self).items():
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"KeypointFitConfig.{k} must be finite and >= 0, got {v}")
        if self.robust_scale <= 0 or self.scan_samples < 1 or self.model_samples < 1:
            raise ValueError("robust_scale, scan_samples and model_samples must be positive")


def load_keypoint_config(path) -> KeypointFitConfig:
    """Read a :class:`KeypointFitConfig` from YAML; unknown keys and wrong types are one-line errors."""
    from blsm.config import config_from_dict
    from blsm.io import read_yaml

    return config_from_dict(KeypointFitConfig, read_yaml(path, "keypoint fit config"), str(path))


# ------------------------------------------------------------------------------------------------
# The keypoint operator A_kp


@dataclass
class KeypointSet:
    """The keypoint operator A_kp of Eq. 6.4: named joints and surface points of the posed model.

    Attributes:
        names: the K keypoint names.
        joint: (K,) long, the joint index of a joint keypoint, -1 for a surface point.
        vertices: (K, 3) long template vertex indices of each surface point's triangle.
        bary: (K, 3) barycentric weights (rows of joint keypoints are unused).
    """

    names: list[str]
    joint: torch.Tensor
    vertices: torch.Tensor
    bary: torch.Tensor

    @classmethod
    def of_model(cls, model, names: Sequence[str] | None = None) -> KeypointSet:
        """The model's keypoints (``model.keypoint_names``), or the named subset, in ``names`` order."""
        names = list(model.keypoint_names) if names is None else [str(n) for n in names]
        unknown = [n for n in names if n not in model.keypoint_names]
        if unknown:
            raise ValueError(f"unknown keypoint names {unknown[:5]} (the model has {model.keypoint_names[:4]}...)")
        idx = torch.tensor([model.keypoint_names.index(n) for n in names], dtype=torch.long)
        return cls(names, model.keypoint_joint[idx].clone(), model.keypoint_vertices[idx].long().clone(),
                   model.keypoint_weights[idx].float().clone())

    @classmethod
    def of_selection(cls, selection: LandmarkSelection) -> KeypointSet:
        """Surface landmarks (A_lm of Eq. 5.13) as keypoints."""
        k = len(selection)
        return cls(list(selection.names), torch.full((k,), -1, dtype=torch.long),
                   selection.vertices.long().clone(), selection.bary.float().clone())

    def __len__(self) -> int:
        return len(self.names)

    def evaluate(self, surface: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
        """(B, K, 3) keypoints from (B, K, 3, 3) posed triangle corners and (B, J, 3) posed joints."""
        surf = (surface * self.bary.to(surface.dtype)[..., None]).sum(2)
        from_joint = joints[:, self.joint.clamp(min=0)]
        return torch.where((self.joint >= 0)[None, :, None], from_joint, surf)


# ------------------------------------------------------------------------------------------------
# Pure terms


def geman_mcclure(d2: torch.Tensor, scale: float) -> torch.Tensor:
    """Geman-McClure ``rho(d^2) = s^2 d^2 / (s^2 + d^2)``: ~d^2 near 0, at most s^2 (same unit as d2)."""
    s2 = scale * scale
    return s2 * d2 / (s2 + d2)


# ------------------------------------------------------------------------------------------------
# The fit


@dataclass
class KeypointFit:
    """Result of :func:`fit_keypoints` / :func:`fit_shape` for T frames of G subjects (detached).

    Attributes:
        groups: (T,) long, the subject of each frame.
        bone: (G, Kb) bone coefficients c_b. shape: (G, Ks) shape coefficients c_s.
        angles: (T, 47) radians. global_orient: (T, 3) axis-angle. transl: (T, 3) metres.
        keypoint_error: (T,) confidence-weighted RMS keypoint distance, metres (robust weights aside).
    """

    groups: torch.Tensor
    bone: torch.Tensor
    shape: torch.Tensor
    angles: torch.Tensor
    global_orient: torch.Tensor
    transl: torch.Tensor
    keypoint_error: torch.Tensor

    def offsets(self, model) -> torch.Tensor:
        """(T, V, 3) T-pose template offsets ``c_b P_bc + V_s(c_s)`` per frame (Eqs. 7, 8)."""
        return _offsets(model, self.bone, self.shape)[self.groups]

    def bone_scales(self, model) -> torch.Tensor:
        """(T, J) bone scales b of each frame (Eq. 4)."""
        return bone_scales(self.bone, model.bone_mean, model.bone_basis)[self.groups]

    def stage1(self, model) -> Stage1:
        """The fit as a :class:`Stage1` (per frame) for :func:`blsm.learn.registration.surface_fit.refine`."""
        return Stage1(self.bone_scales(model), self.angles, self.global_orient, self.transl,
                      self.keypoint_error, self.shape[self.groups], self.offsets(model))

    def vertices(self, model) -> torch.Tensor:
        """(T, V, 3) the posed model meshes, metres."""
        with torch.no_grad():
            return pose(model, model.template + self.offsets(model), bone_scales=self.bone_scales(model),
                        angles=self.angles, global_orient=self.global_orient, transl=self.transl).vertices


def _offsets(model, cb: torch.Tensor, cs: torch.Tensor | None) -> torch.Tensor:
    """(G, V, 3) ``c_b P_bc (+ V_s(c_s))``."""
    out = torch.einsum("gk,kvc->gvc", cb, model.bone_correctives.to(cb.dtype))
    if cs is not None and cs.shape[-1] > 0:
        out = out + model.shape_decoder(cs)
    return out


class _Problem:
    """Parameters and the posed keypoints of T frames of G subjects."""

    def __init__(self, model, kps: KeypointSet, targets: torch.Tensor, conf: torch.Tensor,
                 groups: torch.Tensor, cfg: KeypointFitConfig) -> None:
        self.model, self.kps, self.cfg = model, kps, cfg
        dtype = model.template.dtype
        self.mask = torch.isfinite(targets).all(-1) & (conf > 0)  # (T, K)
        self.w = torch.where(self.mask, conf.to(dtype), torch.zeros((), dtype=dtype))
        self.targets = torch.where(self.mask[..., None], targets.to(dtype), torch.zeros((), dtype=dtype))
        self.groups = groups
        self.vidx = kps.vertices.reshape(-1)
        self.sub_w = model.weights[self.vidx]

    def keypoints(self, cb, cs, x, go, tr, full: bool = False):
        """Posed keypoints (T, K, 3), joints (T, J, 3), angles (T, D) and, if ``full``, vertices."""
        m = self.model
        b = bone_scales(cb, m.bone_mean, m.bone_basis)[self.groups]
        offs = _offsets(m, cb, cs)[self.groups]  # (T, V, 3)
        if full:
            p = pose(m, m.template + offs, bone_scales=b, pose=x, global_orient=go, transl=tr)
            surf = p.vertices[:, self.vidx]
        else:
            p = pose(m, m.template[self.vidx] + offs[:, self.vidx], bone_scales=b, pose=x,
                     global_orient=go, transl=tr, weights=self.sub_w)
            surf = p.vertices
        kp = self.kps.evaluate(surf.reshape(x.shape[0], -1, 3, 3), p.joints)
        return kp, p.joints, p.angles, (p.vertices if full else None)

    def data(self, kp: torch.Tensor, robust: bool = True, scale: float | None = None) -> torch.Tensor:
        """(T,) Eq. 6.4's data term: confidence-weighted mean of rho(squared distance), m^2
        (Geman-McClure at ``scale``, default ``robust_scale``)."""
        d2 = (kp - self.targets).square().sum(-1)
        if robust:
            d2 = geman_mcclure(d2, self.cfg.robust_scale if scale is None else scale)
        return (d2 * self.w).sum(1) / self.w.sum(1).clamp(min=1e-9)

    def priors(self, cb, cs, theta) -> torch.Tensor:
        cfg = self.cfg
        out = cfg.angle_prior * theta.square().mean(1).sum() + cfg.bone_prior * cb.square().mean(1).sum()
        if cs is not None and cs.shape[-1] > 0:
            out = out + cfg.shape_prior * cs.square().mean(1).sum()
        return out


def _rigid_starts(problem: _Problem) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Two starts (go (T, 3), tr (T, 3)): Kabsch of the trunk keypoints, and the same turned by pi."""
    from scipy.spatial.transform import Rotation

    m, dtype = problem.model, problem.model.template.dtype
    t_n = problem.targets.shape[0]
    zero_x = unconstrained_from_angles(torch.zeros(1, m.num_dofs, dtype=dtype), m.dof_limits, eps=0.1)
    with torch.no_grad():
        cb0 = torch.zeros(int(problem.groups.max()) + 1, m.num_bone_coeffs, dtype=dtype)
        rest = problem.keypoints(cb0, None, zero_x.expand(t_n, -1), None, None)[0].double().numpy()  # (T, K, 3)
    trunk = np.array([n in TRUNK_KEYPOINTS for n in problem.kps.names])
    starts = ([], [])
    for t in range(t_n):
        ok = problem.mask[t].numpy()
        use = ok & trunk if (ok & trunk).sum() >= 3 else ok
        w = problem.w[t].double().numpy()[use]
        src, dst = rest[t][use], problem.targets[t].double().numpy()[use]
        cs_, cd = (src * w[:, None]).sum(0) / w.sum(), (dst * w[:, None]).sum(0) / w.sum()
        rot = Rotation.identity() if use.sum() < 3 else Rotation.align_vectors(dst - cd, src - cs_, weights=w)[0]
        for s, r in enumerate((rot, rot * Rotation.from_rotvec([0.0, np.pi, 0.0]))):
            # Rotation about the root joint (pose()'s global_orient), then the translation of the means.
            root = m.heads[0].double().numpy()
            tr = cd - r.apply(cs_ - root) - root
            starts[s].append((r.as_rotvec(), tr))
    return [(torch.as_tensor(np.stack([a for a, _ in st]), dtype=dtype),
             torch.as_tensor(np.stack([b for _, b in st]), dtype=dtype)) for st in starts]


def fit_keypoints(
    model,
    keypoints: KeypointSet,
    targets: torch.Tensor,
    confidence: torch.Tensor | None = None,
    groups: torch.Tensor | None = None,
    config: KeypointFitConfig | None = None,
    init: KeypointFit | None = None,
    times: torch.Tensor | None = None,
) -> KeypointFit:
    """Eq. 6.4: bone coefficients per subject and pose per frame from 3D keypoints.

    Args:
        model: a :class:`blsm.BLSM`.
        keypoints: A_kp, the K keypoints of the model that ``targets`` locate.
        targets: (T, K, 3) keypoint positions L_t, metres; NaN rows = not detected.
        confidence: (T, K) confidences cf_t in [0, 1] (None: ones).
        groups: (T,) long subject of each frame, 0..G-1 (None: all frames one sequence); frames of a
            group share c_b and are smoothed in order.
        config: settings (defaults if None).
        init: for one frame: a fit to try as a start besides the two Kabsch starts (its pose and
            rigid motion), e.g. the neighbouring frame's.
        times: (T,) seconds of the frames for the smoothing S (:func:`smoothing`, :func:`frame_times`);
            None: ``1 / REFERENCE_FPS`` apart.

    Returns:
        :class:`KeypointFit` with zero shape coefficients.

    Raises:
        ValueError: wrong shapes, or a frame with fewer than 4 usable keypoints.
    """
    cfg = config or KeypointFitConfig()
    dtype = model.template.dtype
    t_n = targets.shape[0] if targets.dim() == 3 else 0
    if targets.dim() != 3 or targets.shape[1:] != (len(keypoints), 3) or t_n == 0:
        raise ValueError(f"keypoint targets must be (T, {len(keypoints)}, 3), got {tuple(targets.shape)}")
    conf = torch.ones(targets.shape[:2], dtype=dtype) if confidence is None else confidence.to(dtype)
    groups = torch.zeros(t_n, dtype=torch.long) if groups is None else groups.long()
    if conf.shape != targets.shape[:2] or groups.shape != (t_n,):
        raise ValueError(f"confidence must be (T, K) and groups (T,), got {tuple(conf.shape)}, {tuple(groups.shape)}")
    check_times(times, t_n)
    prob = _Problem(model, keypoints, targets, conf, groups, cfg)
    few = (prob.mask.sum(1) < 4).nonzero()
    if len(few):
        raise ValueError(f"frame {int(few[0])} has {int(prob.mask[int(few[0])].sum())} usable keypoints (need >= 4)")
    if len(groups.unique()) > 1:  # separate subjects: one problem each (a shared L-BFGS converges slower)
        parts = [(g, (groups == g).nonzero()[:, 0]) for g in groups.unique()]
        fits = [fit_keypoints(model, keypoints, targets[i], conf[i], None, cfg,
                              times=None if times is None else times[i]) for _, i in parts]
        return _concat(fits, parts, groups)
    cb = torch.zeros(1, model.num_bone_coeffs, dtype=dtype, requires_grad=True)

    def run(x, go, tr, iters_rigid, iters, scale) -> torch.Tensor:
        def loss(with_priors: bool) -> torch.Tensor:
            kp, joints, theta, _ = prob.keypoints(cb, None, x, go, tr)
            out = prob.data(kp, scale=scale).sum()
            if with_priors:
                out = out + prob.priors(cb, None, theta) + smoothing(joints, theta, groups, cfg, times)
            return out

        lbfgs([go, tr], iters_rigid, lambda: loss(False))
        lbfgs([x, cb, go, tr], iters, lambda: loss(True))
        with torch.no_grad():
            return prob.data(prob.keypoints(cb, None, x, go, tr)[0], scale=scale)

    if t_n > 1:
        # A sequence starts from its frames fitted one by one (facing trials each), c_b their mean.
        one = [fit_keypoints(model, keypoints, targets[t:t + 1], conf[t:t + 1], None, cfg) for t in range(t_n)]
        _propagate(model, keypoints, targets, conf, cfg, one)
        x, go, tr = (torch.cat([getattr(f, k) for f in one]) for k in ("angles", "global_orient", "transl"))
        x = unconstrained_from_angles(x, model.dof_limits, eps=1e-4)
        x, go, tr = (v.clone().requires_grad_(True) for v in (x, go, tr))
        with torch.no_grad():
            cb.copy_(torch.cat([f.bone for f in one]).mean(0, keepdim=True))
        run(x, go, tr, 0, cfg.iterations, cfg.robust_scale)
        return _result(prob, cb, None, x, go, tr)
    # Facing ambiguity: both starts, the better one after a few iterations.
    x0 = unconstrained_from_angles(torch.zeros(1, model.num_dofs, dtype=dtype), model.dof_limits, eps=0.1)
    trials = []
    starts = _rigid_starts(prob)
    if init is not None:  # e.g. the neighbouring frame's fit
        x_i = unconstrained_from_angles(init.angles, model.dof_limits, eps=1e-4)
        starts.append((init.global_orient.clone(), init.transl.clone()))
    for s_i, (go0, tr0) in enumerate(starts):
        if init is not None and s_i == len(starts) - 1:
            x0 = x_i
        with torch.no_grad():
            cb.zero_()
        x, go, tr = (v.clone().requires_grad_(True) for v in (x0, go0, tr0))
        trials.append((float(run(x, go, tr, cfg.rigid_iterations, cfg.trial_iterations, ANNEAL[0])), x, go, tr))
        if cfg.trial_iterations == 0 and init is None:
            break
    x, go, tr = (v.detach().clone().requires_grad_(True) for v in min(trials, key=lambda r: r[0])[1:])
    with torch.no_grad():
        cb.zero_()
    # Graduated robustness: a far keypoint has no gradient under a small scale, so start wide.
    for scale in (*ANNEAL, cfg.robust_scale):
        run(x, go, tr, 0, cfg.iterations // (len(ANNEAL) + 1), max(scale, cfg.robust_scale))
    return _result(prob, cb, None, x, go, tr)


def _propagate(model, keypoints: KeypointSet, targets: torch.Tensor, conf: torch.Tensor,
               cfg: KeypointFitConfig, one: list[KeypointFit], factor: float = 2.0) -> None:
    """Refit, in place, the frames of a sequence whose keypoint error exceeds ``factor`` times the
    median, started from the previous (then the next) frame's fit; the better fit is kept. A frame
    that started in a wrong local minimum (facing, crossed legs) would drag its neighbours through
    the smoothing term."""
    err = torch.stack([f.keypoint_error[0] for f in one])
    bad = (err > factor * err.median()).nonzero()[:, 0].tolist()
    for t in bad:
        for n in (t - 1, t + 1):
            if 0 <= n < len(one) and n not in bad:
                new = fit_keypoints(model, keypoints, targets[t:t + 1], conf[t:t + 1], None, cfg, init=one[n])
                if new.keypoint_error[0] < one[t].keypoint_error[0]:
                    one[t] = new


def _take(fit: KeypointFit, g, frames: torch.Tensor) -> KeypointFit:
    """Frames ``frames`` (all of group ``g``) of a fit, as a one-group fit."""
    return KeypointFit(torch.zeros(len(frames), dtype=torch.long), fit.bone[g][None], fit.shape[g][None],
                       fit.angles[frames], fit.global_orient[frames], fit.transl[frames], fit.keypoint_error[frames])


def _concat(fits: list[KeypointFit], parts, groups: torch.Tensor) -> KeypointFit:
    """One :class:`KeypointFit` of all frames from one fit per group (``parts``: (group, frames))."""
    t_n = groups.shape[0]
    out = {}
    for k in ("angles", "global_orient", "transl", "keypoint_error"):
        v = getattr(fits[0], k)
        full = v.new_zeros((t_n, *v.shape[1:]))
        for f, (_, i) in zip(fits, parts):
            full[i] = getattr(f, k)
        out[k] = full
    n_groups = int(groups.max()) + 1
    bone = fits[0].bone.new_zeros(n_groups, fits[0].bone.shape[1])
    shape = fits[0].shape.new_zeros(n_groups, fits[0].shape.shape[1])
    for f, (g, _) in zip(fits, parts):
        bone[g], shape[g] = f.bone[0], f.shape[0]
    return KeypointFit(groups.clone(), bone, shape, **out)


def _result(prob: _Problem, cb, cs, x, go, tr) -> KeypointFit:
    m = prob.model
    with torch.no_grad():
        kp = prob.keypoints(cb, cs, x, go, tr)[0]
        rms = prob.data(kp, robust=False).sqrt()
        shape = cs if cs is not None else torch.zeros(cb.shape[0], m.num_shape_coeffs, dtype=cb.dtype)
        return KeypointFit(prob.groups.clone(), cb.detach().clone(), shape.detach().clone(),
                           pose_angles(m, x).detach(), go.detach().clone(), tr.detach().clone(), rms)


# ------------------------------------------------------------------------------------------------
# Shape from the scan surface (Eqs. 6.5-6.6)


def scan_samples(vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator,
                 max_triangle_area: float = 0.0) -> np.ndarray:
    """(n, 3) area-uniform points on a scan, leaving out triangles larger than ``max_triangle_area``
    (m^2; 0 keeps all), as Sec. 6.3.4 does against big triangles over holes."""
    f = np.asarray(faces)
    if max_triangle_area > 0:
        tri = vertices[f]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        f = f[area <= max_triangle_area] if (area <= max_triangle_area).any() else f
    fi, w = sample_surface(vertices, f, n, rng)
    return (vertices[f[fi]] * w[..., None]).sum(1)


def near_body(points: np.ndarray, body: np.ndarray, distance: float) -> np.ndarray:
    """(N,) bool: points within ``distance`` metres of the nearest ``body`` vertex (M, 3)."""
    from scipy.spatial import cKDTree

    return cKDTree(body).query(points, k=1, distance_upper_bound=distance)[0] <= distance


def _surface_pairs(meshes: np.ndarray, faces: np.ndarray, scans: Sequence[tuple[np.ndarray, np.ndarray]],
                   crop: float, cfg: KeypointFitConfig, rng: np.random.Generator):
    """Per frame: model samples (faces (P, 3) long, bary (P, 3)) and their MNN scan points (P, 3)
    (Eq. 5.16), scan samples cropped to ``crop`` metres of the body, pairs up to ``crop`` long."""
    out = []
    for t, (sv, sf) in enumerate(scans):
        pts = scan_samples(sv, sf, cfg.scan_samples, rng, cfg.max_triangle_area)
        pts = pts[near_body(pts, meshes[t], crop)]
        fi, w = sample_surface(meshes[t], faces, cfg.model_samples, rng)
        mp = (meshes[t][faces[fi]] * w[..., None]).sum(1)
        im, js = mutual_nearest_neighbours(mp, pts)
        keep = np.linalg.norm(mp[im] - pts[js], axis=1) <= crop
        im, js = im[keep], js[keep]
        out.append((torch.as_tensor(faces[fi[im]]), torch.as_tensor(w[im]), torch.as_tensor(pts[js])))
    return out


def fit_shape(
    model,
    keypoints: KeypointSet,
    targets: torch.Tensor,
    scans: Sequence[tuple[np.ndarray, np.ndarray]],
    start: KeypointFit,
    confidence: torch.Tensor | None = None,
    config: KeypointFitConfig | None = None,
    log: Callable[[str], None] | None = None,
    times: torch.Tensor | None = None,
) -> KeypointFit:
    """Eqs. 6.5-6.6: shape coefficients with bone coefficients and poses on the scan surface.

    Args:
        model: a :class:`blsm.BLSM`. keypoints, targets, confidence: as :func:`fit_keypoints`.
        scans: per frame the scan's (N, 3) vertices and (F, 3) faces, metres.
        start: the :func:`fit_keypoints` result of the same frames (its groups are kept).
        config: settings. log: progress lines, or None.
        times: (T,) seconds of the frames for the smoothing S, as :func:`fit_keypoints`.

    Returns:
        The refined :class:`KeypointFit`.
    """
    cfg = config or KeypointFitConfig()
    dtype = model.template.dtype
    t_n = len(scans)
    if targets.shape[0] != t_n or start.angles.shape[0] != t_n:
        raise ValueError(f"{t_n} scans but {targets.shape[0]} keypoint frames and {start.angles.shape[0]} fitted frames")
    conf = torch.ones(targets.shape[:2], dtype=dtype) if confidence is None else confidence.to(dtype)
    if len(start.groups.unique()) > 1:  # separate subjects: one problem each
        parts = [(g, (start.groups == g).nonzero()[:, 0]) for g in start.groups.unique()]
        fits = [fit_shape(model, keypoints, targets[i], [scans[int(t)] for t in i], _take(start, g, i), conf[i], cfg, log,
                          None if times is None else times[i]) for g, i in parts]
        return _concat(fits, parts, start.groups)
    prob = _Problem(model, keypoints, targets, conf, start.groups, cfg)
    rng = np.random.default_rng(cfg.seed)
    cb = start.bone.clone().requires_grad_(True)
    unit = _shape_unit(model)  # (Ks,) preconditioning: u = 1 moves the surface by about 1 cm
    u = (start.shape.to(dtype) / unit).requires_grad_(model.num_shape_coeffs > 0)
    x = unconstrained_from_angles(start.angles, model.dof_limits, eps=1e-4).clone().requires_grad_(True)
    go, tr = start.global_orient.clone().requires_grad_(True), start.transl.clone().requires_grad_(True)
    faces = model.faces.numpy()
    scans = [(np.asarray(v, np.float64), np.asarray(f, np.int64)) for v, f in scans]

    def loss(pairs) -> torch.Tensor:
        cs = u * unit
        kp, joints, theta, verts = prob.keypoints(cb, cs, x, go, tr, full=True)
        e_mnn = torch.stack([((verts[t, f] * w.to(dtype)[..., None]).sum(1) - p.to(dtype)).square().sum(-1).mean()
                             if len(p) else verts.new_zeros(()) for t, (f, w, p) in enumerate(pairs)])
        out = (cfg.lambda_kp * prob.data(kp) + e_mnn).sum()
        out = out + smoothing(joints, theta, prob.groups, cfg, times)
        return out + prob.priors(cb, cs, theta)

    params = [cb, x, go, tr] + ([u] if model.num_shape_coeffs > 0 else [])
    for r in range(cfg.surface_rounds):
        with torch.no_grad():
            cur = prob.keypoints(cb, u * unit, x, go, tr, full=True)[3].double().numpy()
        crop = cfg.crop_distance if r == 0 else cfg.crop_distance / 2
        pairs = _surface_pairs(cur, faces, scans, crop, cfg, rng)
        lbfgs(params, cfg.surface_iterations, lambda pairs=pairs: loss(pairs))
        if log is not None:
            log(f"  shape round {r}: {int(np.mean([len(p[2]) for p in pairs]))} MNN pairs per frame")
    return _result(prob, cb, (u * unit).detach(), x, go, tr)


def _shape_unit(model) -> torch.Tensor:
    """(Ks,) shape coefficient per centimetre of mean surface motion of each component."""
    dtype = model.template.dtype
    n = model.num_shape_coeffs
    if n == 0:
        return torch.ones(0, dtype=dtype)
    with torch.no_grad():
        eye = torch.eye(n, dtype=dtype)
        eff = (model.shape_decoder(eye) - model.shape_decoder(torch.zeros(1, n, dtype=dtype))).norm(dim=-1).mean(1)
    return 0.01 / eff.clamp(min=1e-6)
