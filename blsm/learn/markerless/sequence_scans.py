"""Stand-in 4D scan sequences and stand-in keypoints, for registration from keypoints (thesis Sec. 6.3).

* :func:`make_sequence`: one Anny subject (:func:`blsm.learn.scans.population.sample_subject`) posed
  along a motion clip of the motion library (``blsm/mocap/library.py``), one ``blsm-scan`` per frame
  with the population's scanner artefacts (:class:`blsm.learn.scans.population.Artefacts`, props
  included), colours (:func:`blsm.learn.scans.scan_paint.paint_body`) and ground truth (``gt_points``,
  ``gt_joints``, ``gt_angles``, ...), as :mod:`blsm.learn.scans.population` makes them.
* :func:`truth_keypoints`: the model's keypoints (``model.keypoint_names``) of the true body: the
  true joints (``gt_joints``) and the surface keypoints on ``gt_points``
  (:func:`blsm.learn.markerless.keypoints.true_keypoints`); for scans without ``gt_joints``, the BLSM model
  at the true pose with bone and shape coefficients fitted to ``gt_points``. A stand-in for
  detected keypoints, not a detector.
* :func:`perturb_keypoints`: detector-like errors on them: Gaussian noise, dropouts, a left/right
  swap.

Units and conventions: metres, radians, Y up, the body faces +Z at rest, +X is the body's left.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm.learn.posing import pose
from blsm.learn.registration.keypoint_fit import KeypointSet
from blsm.learn.registration.landmark_fit import lbfgs

__all__ = ["make_sequence", "perturb_keypoints", "truth_keypoints"]


def truth_keypoints(model, scan: Any, names: list[str] | None = None, iterations: int = 60) -> tuple[list[str], np.ndarray]:
    """The model's keypoints ``names`` (default: those MediaPipe gives) of the true body of a stand-in scan.

    With ``gt_joints``: :func:`blsm.learn.markerless.keypoints.true_keypoints`. Without:
    bone and shape coefficients and a rigid correction are fitted to ``gt_points`` (all template
    vertices, exact correspondence) at the true angles; the keypoints are those of that model body.

    Returns:
        (names (K,), points (K, 3) metres).
    """
    from blsm.learn.markerless.keypoints import BLSM_NAMES, true_keypoints

    names = list(BLSM_NAMES) if names is None else list(names)
    if getattr(scan, "gt_joints", None) is not None and getattr(scan, "gt_points", None) is not None:
        return names, true_keypoints(scan, model, names)
    if getattr(scan, "gt_points", None) is None or getattr(scan, "gt_angles", None) is None:
        raise ValueError(f"{scan.meta.get('id', 'scan')}: no ground truth (gt_points, gt_angles) for stand-in keypoints")
    dtype = model.template.dtype
    gt = torch.as_tensor(np.asarray(scan.gt_points), dtype=dtype)[None]
    ang = torch.as_tensor(np.asarray(scan.gt_angles), dtype=dtype)[None]
    go = torch.as_tensor(np.asarray(scan.gt_global_orient), dtype=dtype)[None].clone().requires_grad_(True)
    tr = torch.as_tensor(np.asarray(scan.gt_transl), dtype=dtype)[None].clone().requires_grad_(True)
    cb = torch.zeros(1, model.num_bone_coeffs, dtype=dtype, requires_grad=True)
    cs = torch.zeros(1, model.num_shape_coeffs, dtype=dtype, requires_grad=True)

    def body():
        from blsm.kinematics import bone_scales

        offs = torch.einsum("gk,kvc->gvc", cb, model.bone_correctives) + model.shape_decoder(cs)
        return pose(model, model.template + offs, bone_scales=bone_scales(cb, model.bone_mean, model.bone_basis),
                    angles=ang, global_orient=go, transl=tr)

    lbfgs([cb, cs, go, tr], iterations, lambda: (body().vertices - gt).square().sum(-1).mean()
          + 1e-6 * (cb.square().mean() + cs.square().mean()))
    kps = KeypointSet.of_model(model, names)
    with torch.no_grad():
        p = body()
        pts = kps.evaluate(p.vertices[:, kps.vertices], p.joints)[0]
    return list(kps.names), pts.double().numpy()


def perturb_keypoints(points: np.ndarray, names: list[str], rng: np.random.Generator, noise: float = 0.02,
                      dropout: float = 0.1, swap: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Detector-like errors: isotropic Gaussian noise (RMS ``noise`` metres in 3D), each keypoint
    missing with probability ``dropout`` (NaN, confidence 0), and with probability ``swap`` one
    left/right pair exchanged (the error a 2D detector makes on a side view).

    Returns:
        (points (K, 3), confidence (K,) in (0, 1]).
    """
    p = np.asarray(points, np.float64) + rng.normal(0.0, noise / np.sqrt(3.0), size=np.shape(points))
    conf = rng.uniform(0.6, 1.0, size=len(p))
    if rng.random() < swap:
        pairs = [(i, names.index(_mirror(n))) for i, n in enumerate(names) if _mirror(n) in names and _mirror(n) != n]
        i, j = pairs[int(rng.integers(len(pairs)))]
        p[[i, j]] = p[[j, i]]
    miss = rng.random(len(p)) < dropout
    p[miss] = np.nan
    conf[miss] = 0.0
    return p, conf


def _mirror(name: str) -> str:
    for a, b in (("_l", "_r"), ("left_", "right_")):
        if name.endswith(a):
            return name[: -len(a)] + b
        if name.endswith(b):
            return name[: -len(b)] + a
        if name.startswith(a):
            return b + name[len(a):]
        if name.startswith(b):
            return a + name[len(b):]
    return name


def make_sequence(
    out: str | Path,
    clip: str | Path,
    frames: int = 30,
    step: int = 1,
    start: int = 0,
    subject: int = 0,
    seed: int = 7,
    yaw: float = 0.5,
    artefacts: Any = None,
    model=None,
) -> list[Path]:
    """Write ``frames`` stand-in scans of one subject posed along a motion clip, ``frame_0000.npz``...

    Args:
        out: the folder (``scans`` of the sequence, and ``sequence.json``).
        clip: a motion library clip (``.npz`` of ``blsm mocap``), its angles drive the subject.
        frames, step, start: the clip frames ``start, start + step, ...``; each scan's meta keeps its
            time in the clip (``time``, seconds), its index in the sequence (``pose``) and the
            sequence's frame rate (``fps``), which the temporal smoothing of ``blsm register
            --sequence`` reads (:func:`blsm.learn.registration.temporal.frame_times`).
        subject: subject index for :func:`blsm.learn.scans.population.sample_subject` (with ``seed``).
        yaw: rotation of the whole sequence about Y, radians (the clip's own root motion is kept).
        artefacts: :class:`blsm.learn.scans.population.Artefacts` (default: the population's).
        model: the BLSM model (default: the packaged rig).

    Returns:
        The written scan paths, in frame order.
    """
    from scipy.spatial.transform import Rotation

    import blsm
    from blsm.build_anny import anny_bone_groups, barycentric_interpolate
    from blsm.joint_limits import angles_from_unconstrained
    from blsm.learn.scans.format import Scan, landmark_names, landmark_points, save_scan
    from blsm.learn.scans.population import (
        Artefacts,
        anny_model,
        anny_rig,
        hole_vertices,
        kept_vertices,
        make_scan_mesh,
        pose_anny,
        rest_bodies,
        sample_subject,
    )  # fmt: skip
    from blsm.learn.scans.scan_paint import add_props, paint_body
    from blsm.mocap.library import load_clip
    from blsm.model import DEFAULT_RIG

    model = blsm.load(DEFAULT_RIG) if model is None else model
    c = load_clip(clip)
    idx = [start + k * step for k in range(frames)]
    if idx[-1] >= c.num_frames:
        raise ValueError(f"{clip}: {c.num_frames} frames, need frame {idx[-1]} ({frames} frames, step {step})")
    out = Path(out)
    rig, art = anny_rig(model), (Artefacts() if artefacts is None else artefacts)
    sub = sample_subject(subject, seed)
    bodies = rest_bodies(model, [sub["phenotype"]], [sub["local_changes"]])
    turn = Rotation.from_rotvec([0.0, yaw, 0.0])
    ang = angles_from_unconstrained(torch.as_tensor(c.pose[idx], dtype=model.dof_limits.dtype), model.dof_limits).double()
    orient = (turn * Rotation.from_rotvec(c.global_orient[idx])).as_rotvec()
    # The clip's root path, turned with the body, from the origin (the root starts at model.heads[0]).
    path = turn.apply(c.transl[idx] - c.transl[idx[0]])
    lm_names = landmark_names()
    labels = list(anny_model().bone_labels)
    groups = [g[0] for g in anny_bone_groups(labels)]
    paint = paint_body(bodies.vertices[0], rig.weights, labels, sub["phenotype"], np.random.default_rng([seed, subject, 4]))
    paths = []
    for k in range(frames):
        one = type(bodies)(bodies.vertices, bodies.heads)
        posed, heads = pose_anny(model, rig, one, ang[k:k + 1], torch.as_tensor(orient[k:k + 1]),
                                 torch.as_tensor(path[k:k + 1]), return_heads=True)
        gt = barycentric_interpolate(posed, rig.faces, rig.tri, rig.bary)[0]
        rng = np.random.default_rng([seed, subject, 5, k])
        miss, _ = hole_vertices(bodies.vertices[0], bodies.heads[0], rig, art, rng, labels)
        v, f = make_scan_mesh(posed[0], rig.faces, miss, art.noise, rng)
        col = paint[kept_vertices(rig.faces, miss)]
        props: dict[str, list[int]] = {}
        if art.stool or art.floor_markers:
            v, f, col, props = add_props(v, f, col, posed[0], art.stool, art.floor_markers,
                                         np.random.default_rng([seed, subject, 6, k]))
        lm = landmark_points(torch.as_tensor(gt)[None]).numpy()[0]
        lm = lm + rng.normal(0.0, art.landmark_noise / np.sqrt(3.0), size=lm.shape)
        meta = {"id": f"frame_{k:04d}", "subject": f"seq{seed}_{subject:05d}", "pose": k, "split": "test",
                "pose_source": f"{Path(clip).stem}:{idx[k]}", "sequence": Path(clip).stem, "fps": c.fps / step,
                "time": idx[k] / c.fps, "props": props}
        scan = Scan(v, f, lm_names, lm.astype(np.float32), meta, gt.astype(np.float32),
                    ang[k].float().numpy(), orient[k].astype(np.float32), path[k].astype(np.float32),
                    heads[0, groups].astype(np.float32), col)
        paths.append(save_scan(scan, out / f"frame_{k:04d}.npz"))
    (out / "sequence.json").write_text(json.dumps({"clip": str(clip), "frames": idx, "subject": f"seq{seed}_{subject:05d}",
                                                    "seed": seed, "fps": c.fps / step}, indent=1))
    return paths
