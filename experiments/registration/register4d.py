"""Registration from keypoints (thesis Sec. 6.3): a 4D sequence registered together vs frame by frame,
and single held-out scans, against the true correspondence (``gt_points``). See docs/markerless.md.

    python experiments/registration/register4d.py sequence --clip out/motions/002_01.npz --keypoints truth --out out/register4d
    python experiments/registration/register4d.py scans SCAN.npz [...] --keypoints truth --out out/register4d

``--keypoints truth``: the model's keypoints of the true body plus detector-like errors
(:func:`blsm.learn.markerless.sequence_scans.perturb_keypoints`: 2 cm noise, 10 % dropouts, a left/right swap in
10 % of the frames); ``landmarks``: the scans' 74 landmarks (5 mm noise) as keypoints (A_lm);
``mediapipe``: ``blsm.learn.markerless.keypoints.scan_keypoints`` (rendered views, MediaPipe, Eq. 6.3);
``baseline``: the landmark registration (:func:`blsm.learn.registration.register.register`, Eqs. 5.13-5.25);
``detector``: the same, with the landmarks located by the learnt detector on the renders
(:mod:`blsm.learn.markerless.landmarks`, ``--detector FILE``); ``exact``: the ceiling of keypoint
registration, the model's keypoints of the true body with no noise, dropout or swap (confidence 1),
plus with ``--extra`` the exact positions of more points: ``face`` (10 face landmarks), ``hands``
(12 hand landmarks), ``spine`` (the pelvis, spine and neck joints), ``torso`` (14 torso landmarks),
as a face, hand or body detector might add them (docs/markerless.md, "The ceiling")::

    python experiments/registration/register4d.py scans SCANS... --keypoints exact --extra hands,spine
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

import blsm
from blsm.learn.markerless.sequence_scans import make_sequence, perturb_keypoints, truth_keypoints
from blsm.learn.registration.keypoint_fit import KeypointFitConfig
from blsm.learn.registration.landmark_fit import default_selection
from blsm.learn.registration.register import KeypointTargets, register_keypoints, scan_data
from blsm.learn.registration.register_config import DEFAULT_CONFIG, load_config
from blsm.learn.registration.registrations import save_registration
from blsm.learn.scans.format import load_scan

EXTRA = {  # --keypoints exact --extra: landmark names of blsm/data/landmarks.yaml, or "+joint" model keypoints
    "face": ["pronasale", "sellion", "menton", "tragion_l", "tragion_r", "infraorbitale_l", "infraorbitale_r",
             "gonion_l", "gonion_r", "glabella"],
    "hands": [f"{n}_{s}" for s in "lr" for n in ("radial_styloid", "ulnar_styloid", "mcp2", "mcp5", "dactylion", "thumb_tip")],
    "spine": ["+pelvis", "+spine_01", "+spine_02", "+spine_03", "+neck"],
    "torso": ["suprasternale", "substernale", "omphalion", "cervicale", "back_t8", "back_waist", "nipple_l", "nipple_r",
              "iliocristale_l", "iliocristale_r", "asis_l", "asis_r", "psis_l", "psis_r"],
}


def exact_targets(model, scans, extra: list[str]):
    """The ceiling: exact model keypoints of the true body (MediaPipe's 21 names, plus ``+joint``
    extras) and exact landmark points (A_lm of ``gt_points``), confidence 1; their A_kp."""
    from blsm.learn.markerless.keypoints import BLSM_NAMES
    from blsm.learn.registration.keypoint_fit import KeypointSet

    names = [*BLSM_NAMES, *(e[1:] for e in extra if e.startswith("+"))]
    marks = [e for e in extra if not e.startswith("+")]
    sel = default_selection(model)
    idx = [sel.names.index(n) for n in marks]
    sub = type(sel)(marks, sel.vertices[idx], sel.bary[idx])  # A_lm of the extra landmarks
    kps = KeypointSet.of_model(model, names)
    if marks:
        lm = KeypointSet.of_selection(sub)
        kps = KeypointSet(kps.names + lm.names, torch.cat([kps.joint, lm.joint]), torch.cat([kps.vertices, lm.vertices]),
                          torch.cat([kps.bary, lm.bary]))
    out = []
    for s in scans:
        _, pts = truth_keypoints(model, s, names)
        lms = sub.select(torch.as_tensor(np.asarray(s.gt_points, np.float64))[None])[0].numpy()
        out.append(KeypointTargets(kps.names, np.concatenate([pts, lms]), np.ones(len(kps.names)),
                                   {"stand_in": "exact keypoints"}))
    return out, kps


def targets_of(model, scans, how: str, seed: int, noise: float, cache: Path | None = None):
    """Per scan :class:`KeypointTargets` and the selection (for landmarks) or None.

    ``cache``: a folder of MediaPipe keypoints per scan, named by its id and its mesh's SHA-256, so that
    a sweep of fitting settings detects once; None detects every time."""
    rng = np.random.default_rng(seed)
    if how == "landmarks":
        sel = default_selection(model)
        out = [KeypointTargets(sel.names, scan_data(s, sel, s.meta["id"]).landmarks, np.ones(len(sel)))
               for s in scans]
        return out, sel
    if how == "truth":
        out = []
        for s in scans:
            names, pts = truth_keypoints(model, s)
            p, c = perturb_keypoints(pts, names, rng, noise=noise)
            out.append(KeypointTargets(names, p, c, {"stand_in": f"truth + {noise * 1000:.0f} mm noise"}))
        return out, None
    from blsm.learn.markerless.keypoints import scan_keypoints

    out = []
    for s in scans:
        digest = _scan_digest(s) if cache is not None else None
        cached = cache / f"{s.meta['id']}_{digest[:16]}.json" if cache is not None else None
        if cached is not None and cached.exists():  # the same scan's MediaPipe keypoints of an earlier run
            d = json.loads(cached.read_text())
            out.append(KeypointTargets(d["names"], np.asarray(d["points"], np.float64), np.asarray(d["confidence"]),
                                       d["info"]))
            continue
        k = scan_keypoints(s, where=s.meta["id"])  # MediaPipe
        t = KeypointTargets(list(k.names), np.asarray(k.points), np.asarray(k.confidence),
                            {"views_with_person": getattr(k, "views_with_person", None)})
        if cached is not None:
            cache.mkdir(parents=True, exist_ok=True)
            tmp = cached.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_text(json.dumps({"scan_sha256": digest, "names": t.names,
                                       "points": [[None if not np.isfinite(c) else float(c) for c in p] for p in t.points],
                                       "confidence": t.confidence.tolist(), "info": t.info}))
            tmp.replace(cached)
        out.append(t)
    return out, None


def _scan_digest(scan) -> str:
    """SHA-256 of a scan's vertices and faces: a keypoint cache entry belongs to exactly this mesh."""
    import hashlib

    h = hashlib.sha256(np.ascontiguousarray(scan.vertices, np.float32).tobytes())
    h.update(np.ascontiguousarray(scan.faces, np.int64).tobytes())
    return h.hexdigest()


def errors(regs, scans) -> dict:
    """Per-frame correspondence error, temporal accelerations (mm/frame^2) and shape spread."""
    v = np.stack([r.vertices for r in regs]).astype(np.float64)
    g = np.stack([s.gt_points for s in scans]).astype(np.float64)
    per = np.linalg.norm(v - g, axis=-1).mean(1) * 1000
    out = {"error_mean_mm": float(per.mean()), "error_max_frame_mm": float(per.max()), "per_frame_mm": per.tolist()}
    if len(regs) >= 3:
        acc = lambda x: x[2:] - 2 * x[1:-1] + x[:-2]  # noqa: E731
        out["accel_error_mm"] = float(np.linalg.norm(acc(v) - acc(g), axis=-1).mean() * 1000)
        out["accel_mm"] = float(np.linalg.norm(acc(v), axis=-1).mean() * 1000)
        out["accel_truth_mm"] = float(np.linalg.norm(acc(g), axis=-1).mean() * 1000)
    if len(regs) >= 4:
        jer = lambda x: x[3:] - 3 * x[2:-1] + 3 * x[1:-2] - x[:-3]  # noqa: E731
        out["jerk_mm"] = float(np.linalg.norm(jer(v), axis=-1).mean() * 1000)
        out["jerk_truth_mm"] = float(np.linalg.norm(jer(g), axis=-1).mean() * 1000)
    # Shape spread: the T-pose person (template + displacement) per frame, distance to the mean.
    tpose = np.stack([r.displacement for r in regs]).astype(np.float64)
    out["tpose_spread_mm"] = float(np.linalg.norm(tpose - tpose.mean(0), axis=-1).mean() * 1000)
    out["bone_scale_spread"] = float(np.stack([r.bone_scales for r in regs]).std(0).mean())
    if all("shape_coeffs" in r.meta for r in regs):  # the person at rest (Eqs. 4, 7, 8), no V_D
        from blsm.learn.posing import pose

        model = blsm.load()
        cb = torch.tensor([r.meta["bone_coeffs"] for r in regs], dtype=torch.float32)
        cs = torch.tensor([r.meta["shape_coeffs"] for r in regs], dtype=torch.float32)
        with torch.no_grad():
            offs = torch.einsum("gk,kvc->gvc", cb, model.bone_correctives) + model.shape_decoder(cs)
            rest = pose(model, model.template + offs, bone_scales=torch.as_tensor(np.stack([r.bone_scales for r in regs]))).vertices
        rest = rest.double().numpy()
        out["rest_shape_spread_mm"] = float(np.linalg.norm(rest - rest.mean(0), axis=-1).mean() * 1000)
    out["stage1_error_mean_mm"] = float(np.mean([r.meta.get("stage1_error_mean_mm", np.nan) for r in regs]))
    # Off the true surface (along its normal) and along it, and by body part, as docs/registration_floor.md.
    from blsm.mesh import vertex_normals

    model = blsm.load()
    faces = model.faces.numpy()
    d = v - g
    off = np.stack([np.abs((d[i] * vertex_normals(g[i], faces)).sum(-1)) for i in range(len(g))])
    along = np.sqrt(np.maximum((d * d).sum(-1) - off**2, 0))
    out["off_surface_mm"], out["along_surface_mm"] = float(off.mean() * 1000), float(along.mean() * 1000)
    dist = np.linalg.norm(d, axis=-1) * 1000
    parts = model.vertex_parts.numpy()
    out["by_part_mm"] = {n: float(dist[:, parts == i].mean()) for i, n in enumerate(model.part_names) if (parts == i).any()}
    return out


def detected_landmarks(scans, weights):
    """The scans with their landmarks from the learnt detector, and the detection's errors."""
    from blsm.learn.markerless.landmarks import detect_landmarks, with_landmarks
    from blsm.learn.scans.format import landmark_points
    from blsm.pose2d.landmark_net import LandmarkDetector

    det = LandmarkDetector(weights)
    out, errs, located, found = [], [], [], []
    for s in scans:
        k = detect_landmarks(s, det, where=s.meta["id"])
        truth = landmark_points(torch.as_tensor(np.asarray(s.gt_points, np.float64))).numpy()
        e = np.linalg.norm(k.points - truth, axis=1) * 1000
        errs.append(e)
        located.append(int(np.isfinite(e).sum()))
        found.append(k.views_with_person / k.views)
        out.append(with_landmarks(s, k, s.meta["id"]))
    e = np.concatenate(errs)
    e = e[np.isfinite(e)]
    extra = {"detector": det.name, "landmark_error_median_mm": float(np.median(e)), "landmark_error_mean_mm": float(e.mean()),
             "landmark_error_rms_mm": float(np.sqrt((e**2).mean())), "landmark_error_p90_mm": float(np.percentile(e, 90)),
             "landmarks_located_mean": float(np.mean(located)), "view_failure_rate": float(1 - np.mean(found)),
             "landmark_error_per_scan_mm": [float(np.nanmean(x)) for x in errs]}
    return out, extra


def _overrides(items: list[str], cls) -> dict:
    """``KEY=VALUE`` settings of the dataclass ``cls``, each value parsed as its field's type."""
    types = {f.name: f.type for f in dataclasses.fields(cls)}
    out = {}
    for item in items:
        key, _, value = item.partition("=")
        if key not in types:
            raise SystemExit(f"register4d: {cls.__name__} has no setting {key!r}")
        out[key] = {"int": int, "float": float, "bool": lambda v: v.lower() in ("1", "true", "yes")}.get(
            str(types[key]), str)(value)
    return out


def run(model, scans, how, sequence, args, tag):
    cfg = load_config(DEFAULT_CONFIG)
    t0 = time.time()
    extra = {}
    if how == "detector":  # landmarks from the learnt detector on the renders, then the landmark registration
        scans, extra = detected_landmarks(scans, args.detector)
        how = "baseline"
    if how == "baseline" and args.landmark_noise > 0:  # extra noise on the scans' own landmarks
        rng = np.random.default_rng(args.seed)
        scans = [replace(s, landmarks=(s.landmarks + rng.normal(0, args.landmark_noise, s.landmarks.shape)).astype(np.float32))
                 for s in scans]
    if how == "baseline":  # the landmark registration (Eqs. 5.13-5.25), batches of 4
        from blsm.learn.registration.register import register

        regs = [r for i in range(0, len(scans), 4) for r in register(model, scans[i:i + 4], cfg)]
    else:  # sequence: one subject; else frame by frame (each its own subject, no smoothing; batched)
        kps, sel = None, None
        if how == "exact":  # exact targets come with their own A_kp
            targets, kps = exact_targets(model, scans, [n for e in args.extra.split(",") if e for n in EXTRA[e]])
        else:
            targets, sel = targets_of(model, scans, how, args.seed, args.noise, args.keypoint_cache)
            if args.regressor is not None:  # A_kp learnt for the detector (blsm.learn.markerless.keypoint_regressor)
                from blsm.learn.markerless.keypoint_regressor import load_keypoint_regressor

                kps = load_keypoint_regressor(args.regressor, model.template.shape[0])
        kcfg = KeypointFitConfig(**_overrides(args.fit, KeypointFitConfig))
        cfg = dataclasses.replace(cfg, **_overrides(args.stage2, type(cfg)))
        regs = register_keypoints(model, scans, targets, cfg, keypoint_config=kcfg, sequence=sequence, selection=sel,
                                  keypoints=kps, stage2_keypoints=args.stage2_keypoints)
    res = {"seconds": time.time() - t0, **errors(regs, scans), **extra}
    folder = args.out / tag
    folder.mkdir(parents=True, exist_ok=True)
    for r, s in zip(regs, scans):
        save_registration(r, folder / f"{s.meta['id']}.npz")
    print(f"{tag}: {json.dumps({k: v for k, v in res.items() if k != 'per_frame_mm'})}", file=sys.stderr, flush=True)
    return res


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=["sequence", "scans"])
    ap.add_argument("paths", nargs="*", type=Path)
    ap.add_argument("--clip", type=Path, default=Path("out/motions/002_01.npz"))
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--step", type=int, default=2)
    ap.add_argument("--keypoints", default="truth", help="truth | landmarks | mediapipe | baseline | detector | exact")
    ap.add_argument("--extra", default="", help=f"--keypoints exact: more exact points, any of {','.join(EXTRA)}")
    ap.add_argument("--noise", type=float, default=0.02)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--modes", default="together,single")
    ap.add_argument("--regressor", type=Path, default=None,
                    help="keypoint regressor file (A_kp learnt for the detector; default: the name mapping)")
    ap.add_argument("--landmark-noise", type=float, default=0.0,
                    help="--keypoints baseline: Gaussian noise per axis added to the scans' landmarks, metres")
    ap.add_argument("--detector", type=Path, default=None,
                    help="landmark detector file for --keypoints detector (default: the packaged one)")
    ap.add_argument("--out", type=Path, default=Path("out/register4d"))
    ap.add_argument("--fit", action="append", default=[], metavar="KEY=VALUE",
                    help="a KeypointFitConfig setting (Eqs. 6.4-6.6), repeatable")
    ap.add_argument("--stage2", action="append", default=[], metavar="KEY=VALUE",
                    help="a RegisterConfig setting of stage 2 (Eqs. 5.14-5.25), repeatable")
    ap.add_argument("--stage2-keypoints", type=float, default=0.0,
                    help="weight of the keypoints in stage 2 (a learnt --regressor only; 0: left out)")
    ap.add_argument("--tag", default="", help="appended to the results' name")
    ap.add_argument("--keypoint-cache", type=Path, default=None,
                    help="--keypoints mediapipe: folder of detected keypoints per scan, reused by later runs")
    args = ap.parse_args()
    torch.set_num_threads(1)
    model = blsm.load()
    results = {}
    if args.what == "sequence":
        seq = args.out / f"seq_{args.clip.stem}"
        if not (seq / "sequence.json").exists():
            make_sequence(seq, args.clip, frames=args.frames, step=args.step)
        scans = [load_scan(p) for p in sorted(seq.glob("frame_*.npz"))][: args.frames]
        how = args.keypoints + ("_regressor" if args.regressor is not None else "")
        for mode in args.modes.split(","):
            results[mode] = run(model, scans, args.keypoints, mode == "together", args, f"{seq.name}_{how}_{mode}{args.tag}")
        name = f"{seq.name}_{how}{args.tag}.json"
    else:
        scans = [load_scan(p) for p in args.paths]
        for s, p in zip(scans, args.paths):
            s.meta.setdefault("id", p.stem)
        ids = [s.meta["id"] for s in scans]
        for s, p in zip(scans, args.paths, strict=True):  # populations all start at s00000_00: use the file name
            if ids.count(s.meta["id"]) > 1:
                s.meta["id"] = p.stem
        if len({s.meta["id"] for s in scans}) < len(scans):
            raise SystemExit("register4d: two scans share an id and a file name")
        tag = f"scans_{args.keypoints}" + ("_regressor" if args.regressor is not None else "")
        tag += f"_{args.extra.replace(',', '_')}" if args.keypoints == "exact" and args.extra else ""
        tag += f"_lmnoise{args.landmark_noise * 1000:g}" if args.landmark_noise > 0 else ""
        tag += args.tag
        results["scans"] = run(model, scans, args.keypoints, False, args, tag)
        results["scans"]["ids"] = [s.meta["id"] for s in scans]
        name = f"{tag}.json"
    (args.out / name).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
