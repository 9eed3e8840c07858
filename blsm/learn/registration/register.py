"""Registering the BLSM template to scans (thesis Sec. 5.4.1, Eqs. 5.13-5.25; Sec. 6.3): the driver.

Two stages per scan, batched over scans:

1. :func:`blsm.learn.registration.landmark_fit.fit_landmarks` (Eq. 5.13): joint angles, per-bone global scales
   and the global rigid motion minimising the landmark distances of the posed template;
   then :func:`blsm.learn.registration.surface_fit.fit_surface` refines them (and the initial model's shape) on
   the scan surface (engineering addition, ``surface_rounds``).
2. :func:`blsm.learn.registration.surface_fit.refine` (Eqs. 5.14-5.25): free per-vertex displacements V_D in the
   T-pose frame, ``S^ = LBS(V_T + V_D, T(s, theta))`` with the stage-1 skeleton held fixed.

Without landmarks, :func:`register_keypoints` (thesis Sec. 6.3) starts from 3D keypoints instead:
Eq. 6.4 (:func:`blsm.learn.registration.keypoint_fit.fit_keypoints`), a grid search of the hands' orientation
(:func:`blsm.learn.registration.end_search.search_hands`, an engineering addition), Eqs. 6.5-6.6
(:func:`blsm.learn.registration.keypoint_fit.fit_shape`; after ``hand_search_round`` rounds the hands, and with
``foot_search`` the ankles, are searched again around the fit), then the same free-form stage 2
(Eqs. 5.14-5.25, used instead of Eqs. 6.8-6.9) with no landmark term, on the scan cropped to the
fitted body. Frames of one subject (a 4D sequence) share the bone and shape coefficients and are
smoothed in time, over the frames' times (:func:`blsm.learn.registration.temporal.frame_times`); a frame whose
keypoint error is far above the rest of its sequence is reported on stderr.

The settings are a :class:`blsm.learn.registration.register_config.RegisterConfig`; the results are
:class:`blsm.learn.registration.registrations.Registration` records (``blsm-registration`` files).

Engineering additions (switchable, ``shape_init``/``surface_rounds``): stage 1 also fits the initial
model's shape coefficients to the landmarks, and the surface fit refines skeleton + shape on the
scan surface (MNN + landmarks) before stage 2. The skeleton-only landmark fit of Eq. 5.13 cannot
move soft-tissue landmarks (chest, belly, back): on Anny scans its landmark RMS stays at about 12 mm
even with exact landmarks and a Gauss-Newton solver started at the true pose, i.e. that is the
model's floor, not slow convergence.

Units and conventions: metres, radians, Y up, the body faces +Z at rest, +X is the body's left.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from blsm.learn.posing import pose
from blsm.learn.registration.end_search import search_feet, search_hands
from blsm.learn.registration.keypoint_fit import (
    KeypointFitConfig,
    KeypointSet,
    fit_keypoints,
    fit_shape,
    near_body,
)
from blsm.learn.registration.landmark_fit import LandmarkSelection, Stage1, default_selection, fit_landmarks
from blsm.learn.registration.register_config import DEFAULT_CONFIG, RegisterConfig, load_config
from blsm.learn.registration.registrations import Registration, correspondence_error
from blsm.learn.registration.surface_fit import ScanData, fit_surface, refine
from blsm.learn.registration.temporal import REFERENCE_FPS, frame_times, outlier_frames
from blsm.learn.scans.format import non_manifold_edges

__all__ = [
    "DEFAULT_CONFIG",
    "KeypointTargets",
    "register_keypoints",
    "LandmarkSelection",
    "RegisterConfig",
    "Stage1",
    "default_selection",
    "fit_stage1",
    "load_config",
    "refine",
    "register",
    "scan_data",
    "st1_vertices",
]


def fit_stage1(model, scans: Sequence[ScanData], selection: LandmarkSelection,
               config: RegisterConfig) -> tuple[Stage1, Stage1]:
    """Stage 1 of B scans: :func:`fit_landmarks` (Eq. 5.13), then :func:`fit_surface`.

    Returns:
        (the landmark fit, the surface refit that stage 2 starts from).
    """
    lms = torch.as_tensor(np.stack([d.landmarks for d in scans]), dtype=model.template.dtype)
    st1 = fit_landmarks(model, lms, selection, config)
    return st1, fit_surface(model, scans, st1, selection, config)


def scan_data(scan: Any, selection: LandmarkSelection, where: str) -> ScanData:
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
    bad = non_manifold_edges(f)
    if bad:
        raise ValueError(f"{where}: scan is non-manifold ({bad} edges shared by more than 2 faces)")
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
            ``blsm.learn.scans.format.Scan``.
        config: settings (defaults if None).
        landmark_index: (L,) template vertex indices of the landmarks, with ``landmark_names``;
            or ``selection`` directly; neither means ``blsm.learn.scans.format.template_landmarks``.
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
        data.append(scan_data(s, selection, str(meta.get("id", f"scan {n}"))))
    t0 = time.perf_counter()
    st1_lm, st1 = fit_stage1(model, data, selection, cfg)
    t1 = time.perf_counter()
    if log:
        log(f"stage 1: {len(data)} scans, landmark rms {[round(float(e) * 1000, 2) for e in st1.landmark_error]} mm, "
            f"{t1 - t0:.1f} s")
    v_d, s_hat, stats = refine(model, data, st1, selection, cfg, log)
    t2 = time.perf_counter()
    if log:
        log(f"stage 2: {cfg.iterations} iterations, {t2 - t1:.1f} s")
    seconds = (t2 - t0) / len(scans)
    stage2 = (v_d, s_hat, stats)
    return [_registration(model, s, n, cfg, st1_lm, st1, stage2, seconds) for n, s in enumerate(scans)]


def _registration(
    model, scan: Any, n: int, cfg: RegisterConfig, st1_lm: Stage1, st1: Stage1,
    stage2: tuple[torch.Tensor, torch.Tensor, list[dict[str, float]]], seconds: float,
) -> Registration:
    """The :class:`Registration` of scan ``n`` of a batch: its stage-1 skeleton, stage-2 mesh and
    displacements, and a meta record (ids, errors in mm, settings)."""
    v_d, s_hat, stats = stage2
    meta = dict(getattr(scan, "meta", None) or {})
    info = {
        "scan": meta.get("id"), "subject": meta.get("subject"), "pose": meta.get("pose"),
        "split": meta.get("split"),
        "stage1_landmark_rms_mm": float(st1_lm.landmark_error[n]) * 1000,
        "surface_fit_landmark_rms_mm": float(st1.landmark_error[n]) * 1000,
        "landmark_rms_mm": math.sqrt(stats[n]["lm"]) * 1000,
        "mnn_rms_mm": math.sqrt(stats[n]["mnn"]) * 1000,
        "mnn_pairs": int(stats[n]["pairs"]),
        "stage1_iterations": cfg.stage1_iterations, "iterations": cfg.iterations,
        "seconds": seconds,
        "config": dataclasses.asdict(cfg),
    }
    gt = getattr(scan, "gt_points", None)
    if gt is not None and np.asarray(gt).shape == tuple(s_hat[n].shape):
        reg0 = Registration(st1_vertices(model, st1, n), *([np.zeros(1)] * 5))
        m0, x0 = correspondence_error(reg0, gt)
        m1, x1 = correspondence_error(Registration(s_hat[n].numpy(), *([np.zeros(1)] * 5)), gt)
        info.update(stage1_error_mean_mm=m0, stage1_error_max_mm=x0, error_mean_mm=m1, error_max_mm=x1)
    return Registration(
        vertices=s_hat[n].numpy().astype(np.float32),
        bone_scales=st1.bone_scales[n].numpy().astype(np.float32),
        angles=st1.angles[n].numpy().astype(np.float32),
        global_orient=st1.global_orient[n].numpy().astype(np.float32),
        transl=st1.transl[n].numpy().astype(np.float32),
        displacement=v_d[n].numpy().astype(np.float32),
        meta=info,
    )


def st1_vertices(model, st1: Stage1, n: int) -> np.ndarray:
    """(V, 3) the stage-1 mesh S^_T of scan ``n`` (metres)."""
    with torch.no_grad():
        tmpl = model.template if st1.shape_offsets is None else model.template + st1.shape_offsets[n]
        return pose(model, tmpl, bone_scales=st1.bone_scales[n:n + 1], angles=st1.angles[n:n + 1],
                    global_orient=st1.global_orient[n:n + 1], transl=st1.transl[n:n + 1]).vertices[0].numpy()


# ------------------------------------------------------------------------------------------------
# Registration from keypoints (thesis Sec. 6.3)


@dataclasses.dataclass
class KeypointTargets:
    """3D keypoints of one scan (e.g. ``blsm.learn.markerless.keypoints.ScanKeypoints``, or landmarks).

    Attributes:
        names: K names, of ``model.keypoint_names`` (or of the landmark selection with ``landmarks``).
        points: (K, 3) metres, NaN rows = not found. confidence: (K,) in [0, 1].
        info: JSON-able record for the registration's meta (views, failures, ...).
    """

    names: list[str]
    points: np.ndarray
    confidence: np.ndarray
    info: dict[str, Any] = dataclasses.field(default_factory=dict)


def _stack_targets(model, targets: Sequence[KeypointTargets], selection: LandmarkSelection | None,
                   keypoints: KeypointSet | None = None):
    """The union of the keypoint names as one :class:`KeypointSet` and (T, K, 3), (T, K) tensors."""
    names: list[str] = []
    for t in targets:
        names += [n for n in t.names if n not in names]
    if keypoints is not None:
        idx = [keypoints.names.index(n) for n in names if n in keypoints.names]
        if not idx:
            raise ValueError(f"the keypoint regressor knows none of the targets' keypoints {names[:4]}...")
        kps = KeypointSet([keypoints.names[i] for i in idx], keypoints.joint[idx], keypoints.vertices[idx],
                          keypoints.bary[idx])
    elif selection is not None:
        order = [n for n in selection.names if n in names]
        idx = [selection.names.index(n) for n in order]
        kps = KeypointSet.of_selection(LandmarkSelection(order, selection.vertices[idx], selection.bary[idx]))
    else:
        kps = KeypointSet.of_model(model, names)
    pts = np.full((len(targets), len(kps), 3), np.nan)
    conf = np.zeros((len(targets), len(kps)))
    for i, t in enumerate(targets):
        look = {n: k for k, n in enumerate(t.names)}
        for k, n in enumerate(kps.names):
            if n in look:
                pts[i, k] = np.asarray(t.points, np.float64)[look[n]]
                conf[i, k] = float(np.asarray(t.confidence)[look[n]])
    dtype = model.template.dtype
    return kps, torch.as_tensor(pts, dtype=dtype), torch.as_tensor(conf, dtype=dtype)


def _cropped(scan: Any, body: np.ndarray, distance: float, max_area: float) -> ScanData:
    """The scan's triangles with all corners within ``distance`` of the fitted ``body`` (V, 3) and no
    larger than ``max_area`` (0: any), as :class:`ScanData` without landmarks (stage 2's input)."""
    v = np.asarray(scan.vertices, np.float64)
    f = np.asarray(scan.faces, np.int64)
    keep = near_body(v, body, distance)[f].all(1)
    if max_area > 0:
        tri = v[f]
        keep &= 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) <= max_area
    if keep.sum() < 100:
        keep[:] = True  # nothing near the body: the fit failed; keep the scan rather than nothing
    return ScanData(v, f[keep], np.zeros((0, 3)))


def register_keypoints(
    model,
    scans: Sequence[Any],
    targets: Sequence[KeypointTargets],
    config: RegisterConfig | None = None,
    keypoint_config: KeypointFitConfig | None = None,
    sequence: bool = False,
    selection: LandmarkSelection | None = None,
    crop_distance: float = 0.03,
    keypoints: KeypointSet | None = None,
    progress: bool = True,
    stage2_keypoints: float = 0.0,
) -> list[Registration]:
    """Register scans from 3D keypoints (thesis Sec. 6.3): Eq. 6.4, Eqs. 6.5-6.6, then Eqs. 5.14-5.25.

    Args:
        model: a :class:`blsm.BLSM`.
        scans: T scans (``vertices``, ``faces``, ``meta``; ``gt_points`` when known).
        targets: their keypoints, one :class:`KeypointTargets` per scan.
        config: stage-2 settings (:class:`RegisterConfig`; its landmark weight is set to 0 for detector
            keypoints, kept for landmarks).
        keypoint_config: settings of Eqs. 6.4-6.6.
        sequence: the scans are frames of one subject in time order: one c_b and c_s, poses smoothed
            (Eq. 6.4's S) over the frames' times (``keypoint_config.fps``, else the scans' meta, else
            15 fps: :func:`blsm.learn.registration.temporal.frame_times`); else every scan is its own subject.
            A frame whose keypoint error after Eq. 6.4 or Eqs. 6.5-6.6 is over twice the sequence's
            median and over 10 mm (:func:`blsm.learn.registration.temporal.outlier_frames`) is reported in
            one ``warning:`` line on stderr (whatever ``progress``) and marked
            ``meta["keypoint_outlier"]``.
        selection: the targets are landmarks of this selection (A_lm), not model keypoints.
        crop_distance: stage 2 sees only scan triangles within this distance of the Eq. 6.5 body
            (metres), so that a stool or floor markers in the scan do not pull the surface.
        keypoints: A_kp for the targets' names (e.g. a learnt detector regressor,
            :mod:`blsm.learn.markerless.keypoint_regressor`); default: the model's keypoints of those names.
        progress: print progress lines on stderr.
        stage2_keypoints: with detector keypoints whose A_kp are all surface points (a learnt
            regressor), keep them in stage 2 as Eq. 5.15's landmark term with this weight
            (``lambda_lm``); 0 (the default) leaves them out.

    Returns:
        One :class:`Registration` per scan; the meta records the keypoints and the shared shape.
    """
    cfg = config or RegisterConfig()
    kcfg = keypoint_config or KeypointFitConfig()
    if len(scans) != len(targets) or not scans:
        raise ValueError(f"need one keypoint set per scan, got {len(scans)} scans and {len(targets)} sets")
    log = (lambda s: print(s, file=sys.stderr, flush=True)) if progress else None
    kps, pts, conf = _stack_targets(model, targets, selection, keypoints)
    if stage2_keypoints > 0 and selection is None and bool((kps.joint >= 0).any()):  # before any fitting
        raise ValueError("stage2_keypoints needs keypoints that are all surface points (a learnt A_kp)")
    groups = torch.zeros(len(scans), dtype=torch.long) if sequence else torch.arange(len(scans))
    times = _sequence_times(scans, kcfg.fps, log) if sequence else None
    t0 = time.perf_counter()
    st_kp = fit_keypoints(model, kps, pts, conf, groups, kcfg, times=times)
    t1 = time.perf_counter()
    if log:
        log(f"Eq. 6.4: {len(scans)} frames, keypoint rms {[round(float(e) * 1000, 1) for e in st_kp.keypoint_error]} mm, "
            f"{t1 - t0:.1f} s")
    outliers: set[int] = set()
    _warn_outliers(scans, st_kp, "Eq. 6.4", outliers)
    raw = [(np.asarray(s.vertices, np.float64), np.asarray(s.faces, np.int64)) for s in scans]
    if selection is None:  # detector keypoints say nothing of the hands' orientation
        st_kp = search_hands(model, st_kp, raw)
    k = kcfg.hand_search_round
    if selection is None and 0 < k < kcfg.surface_rounds:  # the hands (and feet) again, on the fitted shape
        first = fit_shape(model, kps, pts, raw, st_kp, conf, dataclasses.replace(kcfg, surface_rounds=k), log,
                          times)
        first = search_hands(model, first, raw, around=True)
        if kcfg.foot_search:
            first = search_feet(model, first, raw)
        rest = dataclasses.replace(kcfg, surface_rounds=kcfg.surface_rounds - k, seed=kcfg.seed + 1)
        st_sh = fit_shape(model, kps, pts, raw, first, conf, rest, log, times)
    else:
        st_sh = fit_shape(model, kps, pts, raw, st_kp, conf, kcfg, log, times)
    _warn_outliers(scans, st_sh, "Eqs. 6.5-6.6", outliers)
    bodies = st_sh.vertices(model).double().numpy()
    data = [_cropped(s, bodies[n], crop_distance, kcfg.max_triangle_area) for n, s in enumerate(scans)]
    if selection is not None or stage2_keypoints > 0:  # surface points: stage 2 keeps Eq. 5.15's landmark term
        sub = LandmarkSelection(kps.names, kps.vertices, kps.bary)
        data = [ScanData(d.vertices, d.faces, pts[n].double().numpy()) for n, d in enumerate(data)]
        cfg2 = cfg if selection is not None else dataclasses.replace(cfg, lambda_lm=stage2_keypoints)
    else:  # detector keypoints are joints and biased points: no landmark term (Eq. 6.8)
        sub = LandmarkSelection([], torch.zeros(0, 3, dtype=torch.long), torch.zeros(0, 3))
        cfg2 = dataclasses.replace(cfg, lambda_lm=0.0)
    if kcfg.stage2_iterations:
        cfg2 = dataclasses.replace(cfg2, iterations=kcfg.stage2_iterations)
    t2 = time.perf_counter()
    v_d, s_hat, stats = refine(model, data, st_sh.stage1(model), sub, cfg2, log)
    t3 = time.perf_counter()
    if log:
        log(f"Eqs. 6.5-6.6: {t2 - t1:.1f} s; stage 2: {cfg2.iterations} iterations, {t3 - t2:.1f} s")
    regs = []
    for n, s in enumerate(scans):
        reg = _registration(model, s, n, cfg2, st_kp.stage1(model), st_sh.stage1(model), (v_d, s_hat, stats),
                            (t3 - t0) / len(scans))
        g = int(groups[n])
        reg.meta.update(
            method="keypoints (thesis Sec. 6.3)", sequence=bool(sequence), frame=n,
            keypoint_names=kps.names, keypoints=[[None if not np.isfinite(c) else round(float(c), 5) for c in p]
                                                 for p in pts[n].tolist()],
            keypoint_confidence=[round(float(c), 4) for c in conf[n]],
            keypoint_rms_mm=float(st_kp.keypoint_error[n]) * 1000,
            shape_keypoint_rms_mm=float(st_sh.keypoint_error[n]) * 1000,
            bone_coeffs=st_sh.bone[g].tolist(), shape_coeffs=st_sh.shape[g].tolist(),
            keypoint_outlier=n in outliers,
            keypoint_config=dataclasses.asdict(kcfg), keypoints_info=targets[n].info,
        )
        gt = getattr(s, "gt_points", None)
        if gt is not None and np.asarray(gt).shape == (model.num_vertices, 3):
            reg.meta["keypoint_fit_error_mean_mm"] = correspondence_error(
                Registration(st1_vertices(model, st_kp.stage1(model), n), *([np.zeros(1)] * 5)), gt)[0]
        if times is not None:
            reg.meta["frame_time_s"] = float(times[n])
        for k in ("stage1_landmark_rms_mm", "surface_fit_landmark_rms_mm", "landmark_rms_mm"):
            reg.meta.pop(k, None)
        regs.append(reg)
    return regs


def _sequence_times(scans: Sequence[Any], fps: float, log: Any) -> torch.Tensor | None:
    """The times of a sequence's frames (:func:`blsm.learn.registration.temporal.frame_times`), checked to increase
    (a ValueError naming the first frame out of order); their spacing logged."""
    times, source = frame_times([getattr(s, "meta", None) for s in scans], fps)
    if times is not None and bool((times[1:] <= times[:-1]).any()):
        i = int((times[1:] <= times[:-1]).nonzero()[0]) + 1
        raise ValueError(f"{_name(scans[i], i)}: frame time {float(times[i]):.4g} s does not follow the "
                         f"previous frame's {float(times[i - 1]):.4g} s ({source}); give the frames in time "
                         "order")
    if log and len(scans) > 1:
        gaps = np.diff(times.numpy()) if times is not None else np.full(len(scans) - 1, 1 / REFERENCE_FPS)
        log(f"temporal smoothing: frames {gaps.min():.4g}-{gaps.max():.4g} s apart ({source})")
    return times


def _name(scan: Any, n: int) -> str:
    """A scan's id (its meta's), else ``frame n``."""
    return str((getattr(scan, "meta", None) or {}).get("id", f"frame {n}"))


def _warn_outliers(scans: Sequence[Any], fit: Any, stage: str, seen: set[int]) -> None:
    """One ``warning:`` line on stderr per frame of a sequence whose keypoint error after ``stage``
    is far above its sequence's (:func:`blsm.learn.registration.temporal.outlier_frames`), once per frame
    (``seen`` collects the reported frames)."""
    err = fit.keypoint_error
    for n in outlier_frames(err, fit.groups):
        if n in seen:
            continue
        seen.add(n)
        med = float(err[fit.groups == fit.groups[n]].median())
        print(f"warning: frame {n} ({_name(scans[n], n)}): keypoint rms {float(err[n]) * 1000:.1f} mm after "
              f"{stage}, over twice the sequence's median {med * 1000:.1f} mm: a wrong fit or bad keypoints "
              "(check the frame spacing, --fps, or register the frame alone)", file=sys.stderr, flush=True)
