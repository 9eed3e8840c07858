"""The commands that learn BLSM from scans: ``blsm scans | register | learn | train | evaluate |
train-smpl``.

One place for their arguments (:func:`add_parsers`, called by :func:`blsm.cli.build_parser`) and
for what each runs. A bad input is one line ``blsm <command>: error: ...`` and exit status 2
(``evaluate`` and ``train-smpl`` print it on stdout, ``learn`` prints the whole message).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from blsm.learn.evaluation.evaluate import DEFAULT_KS

# Help lines of ``blsm --help``.
HELP = {
    "scans": "make a scan population from Anny (the CAESAR / D-FAUST stand-in)",
    "register": "register the template to scans (landmark fit, then free-form; Eqs. 5.13-5.25)",
    "learn": "learn bone basis, correctives, shape and weights from registrations (Eqs. 5.26-5.31)",
    "train": "the whole run: population, registration, learning, evaluation (one config)",
    "evaluate": "held-out errors of BLSM-linear and SMPL-reimpl against the number of coefficients",
    "train-smpl": "train the SMPL-reimpl baseline on registrations (Sec. 5.5.1)",
    "reparam": "reparameterise a model to a new template topology (thesis ch. 3, Eqs. 3.5-3.7)",
    "scan-keypoints": "3D keypoints of a scan from multi-view renders and MediaPipe (Sec. 6.3.1)",
    "train-landmark-detector": "train the 2D landmark detector of markerless registration on stand-in scans",
}


def command(name: str, run: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """``run`` with a ValueError turned into ``blsm NAME: error: <first line>`` on stderr, exit 2."""

    def wrapped(args: argparse.Namespace) -> int:
        try:
            return run(args)
        except ValueError as exc:
            print(f"blsm {name}: error: {str(exc).splitlines()[0]}", file=sys.stderr)
            return 2

    return wrapped


def add_parsers(sub: Any) -> None:
    """Add the learning commands to ``blsm``'s sub-commands, in the order ``blsm --help`` lists them."""
    scans = sub.add_parser("scans", help=HELP["scans"], description="Synthetic scan populations from Anny.")
    scans_sub = scans.add_subparsers(dest="cmd", required=True)
    make = scans_sub.add_parser("make", help="write a scan population folder")
    make.add_argument("--out", type=Path, required=True)
    make.add_argument("--subjects", type=int, required=True)
    make.add_argument("--posed-subjects", type=int, default=0)
    make.add_argument("--poses", type=int, default=0, help="posed scans per posed subject")
    make.add_argument("--seed", type=int, default=0)
    make.add_argument("--test-fraction", type=float, default=0.1)
    make.add_argument("--motions", type=Path, default=None,
                      help="motion library folder (default: the pose prior)")
    make.add_argument("--overwrite", action="store_true")
    make.set_defaults(func=command("scans", cmd_scans_make))

    reg = sub.add_parser(
        "register", help=HELP["register"],
        description="Register the BLSM template to scans (thesis Sec. 5.4.1): landmark fit, then "
                    "free-form refinement; writes one blsm-registration .npz per scan.",
    )  # fmt: skip
    reg.add_argument("scans", nargs="+", type=Path, help="scan files (blsm-scan .npz, or OBJ/PLY/GLB)")
    reg.add_argument("--out", type=Path, required=True, help="output folder")
    reg.add_argument("--landmarks", type=Path, help="the scan's located landmarks, JSON {name: [x, y, z]} "
                     "(default: <scan stem>.landmarks.json beside a mesh; inside a .npz scan)")
    reg.add_argument("--landmark-definitions", type=Path, help="template landmark definitions YAML "
                     "(default: blsm/data/landmarks.yaml via blsm.learn.scans.format)")
    reg.add_argument("--config", type=Path, help="RegisterConfig YAML (default: configs/blsm/register.yaml "
                     "when present, else the thesis' values)")
    reg.add_argument("--model", type=Path, help="BLSM model file (default: the packaged one)")
    reg.add_argument("--batch", type=int, default=4, help="scans registered together (default 4)")
    reg.add_argument("--overwrite", action="store_true", help="replace existing registration files")
    reg.add_argument("--markerless", action="store_true", help="register from detected 3D keypoints even when "
                     "the scans have landmarks (thesis Sec. 6.3; scans without landmarks always are)")
    reg.add_argument("--detector", default="mediapipe", choices=["mediapipe", "landmarks"],
                     help="markerless detector: 'mediapipe' (default) fits MediaPipe Pose keypoints (Eq. 6.4, "
                     "needs .venv-reference); 'landmarks' locates the scan's 74 landmarks with a learnt detector "
                     "(--landmark-detector, blsm train-landmark-detector) and runs the landmark registration")
    reg.add_argument("--landmark-detector", type=Path, default=None,
                     help="landmark detector file for --detector landmarks (blsm train-landmark-detector)")
    reg.add_argument("--views", type=int, default=18, help="rendered views per scan for the detector (18)")
    reg.add_argument("--keypoint-config", type=Path, help="KeypointFitConfig YAML of the keypoint registration "
                     "(Eqs. 6.4-6.6; default: its built-in values)")
    reg.add_argument("--keypoint-regressor", default=None, help="A_kp of Eq. 6.4 learnt for the detector's "
                     "keypoints (blsm.learn.markerless.keypoint_regressor; default: the packaged one for MediaPipe; 'none': "
                     "the detector's names mapped onto the model's keypoints)")
    reg.add_argument("--sequence", action="store_true", help="the scans (or the folder's scans, sorted by "
                     "name) are frames of one subject: one bone and shape, poses smoothed in time (Eq. 6.4)")
    reg.add_argument("--fps", type=float, default=None,
                     help="--sequence: frames per second of the frames as given (each next frame 1/FPS s "
                     "later; e.g. 7.5 for every 4th frame of a 30 fps clip), so that the smoothing follows "
                     "their spacing in time (default: the keypoint config's fps, else the scans' own times "
                     "where they carry them, else 15)")
    reg.set_defaults(func=command("register", cmd_register))

    learn = sub.add_parser(
        "learn", help=HELP["learn"],
        description="Learning the BLSM parameters from registrations (thesis Sec. 5.4.2-5.4.4, "
                    "Eqs. 5.26-5.31).",
    )  # fmt: skip
    learn.add_argument("registrations", nargs="+", type=Path, help="registration files or folders")
    learn.add_argument("--config", type=Path, default=None, help="YAML run config (its train: section)")
    learn.add_argument("--model", type=Path, default=None, help="initial model (default: the packaged one)")
    learn.add_argument("--out", type=Path, required=True, help="learned model file (.npz)")
    learn.add_argument("--report", type=Path, default=None, help="JSON report (default: <out>.report.json)")
    learn.set_defaults(func=command("learn", cmd_learn))

    train = sub.add_parser(
        "train", help=HELP["train"],
        description="``blsm train CONFIG --out MODEL``: scans to a learned BLSM in one command "
                    "(thesis Sec. 5.4).",
    )  # fmt: skip
    train.add_argument("config", type=Path, help="run config YAML (configs/blsm/train_default.yaml)")
    train.add_argument("--out", type=Path, required=True, help="the learned model file (.npz)")
    train.add_argument("--model", default=None,
                       help="initial model (default: the packaged rig, blsm/data/blsm_anny_rig.npz)")
    train.add_argument("--overwrite", action="store_true", help="replace an existing model file")
    train.set_defaults(func=command("train", cmd_train))

    _add_evaluate(sub)

    smpl = sub.add_parser("train-smpl", help=HELP["train-smpl"],
                          description="Train the SMPL-reimpl baseline (Sec. 5.5.1).")
    smpl.add_argument("--model", default=None,
                      help="BLSM model .npz sharing topology/skeleton (default: packaged)")
    smpl.add_argument("--registrations", required=True, help="folder of blsm-registration .npz files")
    smpl.add_argument("--num-coeffs", type=int, default=32, help="PCA shape components kept")
    smpl.add_argument("--iterations", default="100,100,100,300", help="Adam steps of the pose-fit stages")
    smpl.add_argument("--lm-iterations", type=int, default=25)
    smpl.add_argument("--out", required=True, help="output .npz")
    smpl.set_defaults(func=command("train-smpl", cmd_train_smpl))
    from blsm.learn.reparam.cli import add_parser as add_reparam  # blsm reparam (thesis ch. 3)
    add_reparam(sub, HELP["reparam"], command)
    from blsm.learn.markerless.keypoints import add_parser as add_scan_keypoints  # blsm scan-keypoints
    add_scan_keypoints(sub, HELP["scan-keypoints"], command)
    from blsm.learn.markerless.landmark_detector import (
        add_parser as add_detector,  # blsm train-landmark-detector
    )
    add_detector(sub, HELP["train-landmark-detector"], command)


def _add_evaluate(sub: Any) -> None:
    ev = sub.add_parser("evaluate", help=HELP["evaluate"],
                        description="Held-out evaluation of BLSM-linear against SMPL-reimpl "
                                    "(thesis Sec. 5.5.2).")
    ev.add_argument("--model", default=None, help="BLSM model .npz (default: the packaged one)")
    ev.add_argument("--baseline", default=None, help="SMPL-reimpl .npz (blsm.learn.evaluation.smpl_reimpl)")
    ev.add_argument("--registrations", required=True, help="folder of blsm-registration .npz files")
    ev.add_argument("--scans", default=None, help="population / scan folder for ground truth")
    ev.add_argument("--split", default="test", choices=("train", "test", "all"))
    ev.add_argument("--out", default="docs/blsm_evaluation.md", help="markdown file to write")
    ev.add_argument("--ks", default=",".join(map(str, DEFAULT_KS)), help="comma-separated k values")
    ev.add_argument("--iterations", default="100,100,100,300", help="Adam steps of the four stages")
    ev.add_argument("--lm-iterations", type=int, default=25, help="Levenberg-Marquardt polish steps")
    ev.add_argument("--batch", type=int, default=16)
    ev.add_argument("--max-registrations", type=int, default=0, help="0 = all")
    ev.add_argument("--spread", action="store_true",
                    help="with --max-registrations: take them round-robin over the subjects, not the first N")
    ev.add_argument("--no-pose", action="store_true", help="skip pose generalisation")
    ev.add_argument("--targets", default="registrations", choices=("registrations", "ground-truth"),
                    help="fit the registrations, or the true bodies they register (needs gt_points)")
    ev.add_argument("--also", action="append", default=[], metavar="NAME=MODEL.npz",
                    help="another BLSM model to fit alongside (repeatable)")
    ev.set_defaults(func=command("evaluate", cmd_evaluate))


# ------------------------------------------------------------------------------------------------
# The commands


def cmd_scans_make(args: argparse.Namespace) -> int:
    """``blsm scans make``: a population folder of Anny stand-in scans."""
    from blsm.learn.scans.population import make_population

    index = make_population(
        args.out, args.subjects, args.posed_subjects, args.poses, args.seed, args.test_fraction,
        motions=args.motions, overwrite=args.overwrite,
    )  # fmt: skip
    n_scans = sum(len(s["scans"]) for s in index["subjects"])
    print(f"wrote {n_scans} scans of {len(index['subjects'])} subjects to {args.out} in {index['seconds']} s")
    return 0


def cmd_register(args: argparse.Namespace) -> int:
    """``blsm register SCAN [SCAN ...] --out DIR``: one ``blsm-registration`` file per scan.

    A scan is a ``blsm-scan`` ``.npz`` or an OBJ / PLY / GLB mesh whose located landmarks are in
    ``<stem>.landmarks.json`` beside it, or in ``--landmarks FILE`` (one scan only). Scans without
    landmarks (or all, with ``--markerless``) are registered from detected 3D keypoints, and
    ``--sequence`` registers the scans as frames of one subject (thesis Sec. 6.3).
    """
    import blsm
    from blsm.learn.registration.landmark_fit import default_selection, read_landmark_definitions
    from blsm.learn.registration.register import register, scan_data
    from blsm.learn.registration.register_config import DEFAULT_CONFIG, RegisterConfig, load_config
    from blsm.learn.registration.registrations import save_registration
    from blsm.learn.scans.format import load_scan

    torch.set_num_threads(1)
    model = blsm.load(args.model)
    if args.config is not None:
        cfg = load_config(args.config)
    else:
        cfg = load_config(DEFAULT_CONFIG) if DEFAULT_CONFIG.is_file() else RegisterConfig()
    selection = (
        read_landmark_definitions(args.landmark_definitions, model)
        if args.landmark_definitions else default_selection(model)
    )  # fmt: skip
    if args.landmarks is not None and len(args.scans) != 1:
        raise ValueError(f"{args.landmarks}: --landmarks names the landmarks of one scan, "
                         f"got {len(args.scans)} scans")
    if args.batch < 1:
        raise ValueError(f"--batch must be >= 1, got {args.batch}")
    if args.landmark_detector is not None and args.detector != "landmarks":
        raise ValueError(f"{args.landmark_detector}: --landmark-detector needs --detector landmarks")
    if args.fps is not None and not args.sequence:
        raise ValueError("--fps sets the spacing of --sequence frames; add --sequence")
    if args.fps is not None and not (args.fps > 0 and math.isfinite(args.fps)):
        raise ValueError(f"--fps must be a positive number of frames per second, got {args.fps}")
    paths = [q for p in args.scans for q in (_scan_files(p) if p.is_dir() else [p])]
    jobs = []
    for p in paths:
        target = args.out / f"{p.stem}.npz"
        if target.exists() and not args.overwrite:
            raise ValueError(f"{target}: exists (use --overwrite to replace it)")
        scan = load_scan(p, landmarks=args.landmarks, require_landmarks=False)
        scan.meta = {**(getattr(scan, "meta", None) or {})}
        scan.meta.setdefault("id", p.stem)
        if not (args.markerless or args.sequence) and scan.located.any():
            scan_data(scan, selection, str(p))  # fail fast, naming the file
        elif not scan.located.any() and getattr(scan, "colors", None) is None and not args.markerless:
            raise ValueError(f"{p}: no landmarks located and no vertex colours to detect keypoints on "
                             "(give --landmarks, or --markerless to use the untextured renders)")
        jobs.append((scan, target, p))
    detect = args.markerless or any(not s.located.any() for s, _, _ in jobs)
    if detect and args.detector == "landmarks":  # the scans' landmarks from their renders, then as usual
        jobs, detect = _detect_landmarks(jobs, args), False
    if detect or args.sequence:
        return _register_keypoints(model, jobs, cfg, selection, args, detect)
    for i in range(0, len(jobs), args.batch):
        chunk = jobs[i : i + args.batch]
        regs = register(model, [s for s, _, _ in chunk], cfg, selection=selection)
        for reg, (_, target, _) in zip(regs, chunk, strict=True):
            save_registration(reg, target)
            print(f"wrote {target}", file=sys.stderr)
    return 0


def _scan_files(folder: Path) -> list[Path]:
    """The scan files of a folder, sorted by name (the frames of a sequence)."""
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".npz", ".obj", ".ply", ".glb"))
    if not files:
        raise ValueError(f"{folder}: no scan files (.npz, .obj, .ply, .glb)")
    return files


def _detect_landmarks(jobs: list, args: argparse.Namespace) -> list:
    """Each scan with its landmarks located from its renders (``blsm.learn.markerless.landmarks``)."""
    from blsm.learn.markerless.keypoints import MarkerlessConfig
    from blsm.learn.markerless.landmarks import LandmarkDetectionConfig, detect_landmarks, with_landmarks
    from blsm.learn.markerless.multiview import ViewConfig
    from blsm.pose2d.landmark_net import LandmarkDetector

    if args.views < 2:
        raise ValueError(f"--views must be >= 2, got {args.views}")
    detector = LandmarkDetector(args.landmark_detector)
    dcfg = LandmarkDetectionConfig(MarkerlessConfig(views=ViewConfig(views=args.views)))
    out = []
    for s, target, p in jobs:
        found = detect_landmarks(s, detector, dcfg, str(p))
        scan = with_landmarks(s, found, str(p))
        lf = scan.meta["landmarks_from"]
        print(f"{p}: {lf['located']} landmarks located from {lf['views_with_person']}/{lf['views']} views",
              file=sys.stderr)
        out.append((scan, target, p))
    return out


def _register_keypoints(model, jobs: list, cfg, selection, args: argparse.Namespace, detect: bool) -> int:
    """Registration from keypoints (thesis Sec. 6.3): landmarks as keypoints where every scan has
    them (and ``detect`` is off), else MediaPipe keypoints (``blsm.learn.markerless.keypoints``)."""
    import numpy as np

    from blsm.learn.registration.keypoint_fit import load_keypoint_config
    from blsm.learn.registration.register import KeypointTargets, register_keypoints, scan_data
    from blsm.learn.registration.registrations import save_registration

    if args.keypoint_config is not None:
        load_keypoint_config(args.keypoint_config)  # fail before the detector runs
    from blsm.learn.markerless.keypoint_regressor import DEFAULT_REGRESSOR, load_keypoint_regressor

    regressor, path = None, None
    if args.keypoint_regressor != "none":
        path = DEFAULT_REGRESSOR if args.keypoint_regressor is None else Path(args.keypoint_regressor)
        regressor = load_keypoint_regressor(path, model.template.shape[0])

    targets, sel = [], None
    if not detect and all(s.located.any() for s, _, _ in jobs):
        sel = selection
        for s, _, p in jobs:
            targets.append(KeypointTargets(sel.names, scan_data(s, sel, str(p)).landmarks, np.ones(len(sel)),
                                           {"source": "landmarks"}))
    else:
        from blsm.learn.markerless.keypoints import MarkerlessConfig, scan_keypoints
        from blsm.learn.markerless.multiview import ViewConfig
        from blsm.pose2d.detectors import MediaPipeDetector

        if args.views < 2:
            raise ValueError(f"--views must be >= 2, got {args.views}")
        mcfg = MarkerlessConfig(views=ViewConfig(views=args.views))
        detector = MediaPipeDetector()
        for s, _, p in jobs:
            try:
                k = scan_keypoints(s, detector, mcfg, str(p))
            except ValueError as exc:  # name the scan even when the detector's setup failed
                raise ValueError(str(exc) if str(p) in str(exc) else f"{p}: {exc}") from None
            ok = np.isfinite(k.points).all(1)
            if ok.sum() < 4:
                raise ValueError(f"{p}: only {int(ok.sum())} keypoints triangulated (need >= 4)")
            targets.append(KeypointTargets(list(k.names), k.points, k.confidence, {
                "source": "markerless", "detector": k.detector, "views": k.views,
                "a_kp": str(path) if regressor is not None else "model keypoints by name",
                "views_with_person": k.views_with_person, "view_failure_rate": 1 - k.views_with_person / k.views,
                "swapped_views": int(k.per_view.swapped.sum()), "keypoint_views": k.num_views.tolist()}))
    scans = [s for s, _, _ in jobs]
    kcfg = load_keypoint_config(args.keypoint_config) if args.keypoint_config is not None else None
    if args.fps is not None:
        import dataclasses

        from blsm.learn.registration.keypoint_fit import KeypointFitConfig

        kcfg = dataclasses.replace(kcfg or KeypointFitConfig(), fps=args.fps)
    kps = regressor if sel is None else None
    if args.sequence:
        regs = register_keypoints(model, scans, targets, cfg, kcfg, sequence=True, selection=sel, keypoints=kps)
    else:
        regs = [r for i in range(0, len(jobs), args.batch)
                for r in register_keypoints(model, scans[i:i + args.batch], targets[i:i + args.batch], cfg,
                                            kcfg, selection=sel, keypoints=kps)]
    for reg, (_, target, _) in zip(regs, jobs, strict=True):
        save_registration(reg, target)
        print(f"wrote {target}", file=sys.stderr)
    return 0


def cmd_learn(args: argparse.Namespace) -> int:
    """``blsm learn REGISTRATION ... --out MODEL``: the model and its JSON report."""
    from blsm import io
    from blsm.learn.registration.registrations import load_registrations
    from blsm.learn.training.train import TrainConfig, learn_model, load_train_config
    from blsm.model import load

    try:
        cfg = load_train_config(args.config) if args.config is not None else TrainConfig()
        regs = load_registrations(args.registrations)
        data, report = learn_model(load(args.model), regs, cfg)
    except ValueError as exc:
        print(f"blsm learn: error: {exc}", file=sys.stderr)
        return 2
    io.save_model(data, args.out)
    report_path = args.report or args.out.with_suffix(".report.json")
    with io.atomic_write(report_path, "w") as fh:
        json.dump(report, fh, indent=1)
    print(f"[train] wrote {args.out} and {report_path}", file=sys.stderr, flush=True)
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    """``blsm train CONFIG --out MODEL``: the whole pipeline (:mod:`blsm.learn.pipeline`)."""
    from blsm.learn.pipeline import load_config, run

    if args.out.exists() and not args.overwrite:
        raise ValueError(f"{args.out}: exists; pass --overwrite to replace it")
    run(load_config(args.config), args.out, args.model, str(args.config))
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    """``blsm evaluate``: BLSM-linear vs SMPL-reimpl on held-out registrations."""
    import blsm
    from blsm.learn.evaluation.evaluate import EvalConfig, evaluate, write_report
    from blsm.learn.evaluation.fit import BLSMFittable, FitConfig, Fittable
    from blsm.learn.evaluation.smpl_reimpl import SMPLReimplFittable, load_smpl_reimpl
    from blsm.learn.registration.registrations import load_registration_set, spread_over_subjects

    try:
        ks = tuple(int(k) for k in args.ks.split(","))
        iters = tuple(int(i) for i in args.iterations.split(","))
        fitcfg = FitConfig(iterations=iters, lm_iterations=args.lm_iterations)  # type: ignore[arg-type]
        model = blsm.load(args.model)
        regs = load_registration_set(args.registrations, model.num_vertices, args.scans)
        if args.split != "all":
            regs = regs.split(args.split)
        if args.max_registrations > 0:
            n = min(args.max_registrations, regs.vertices.shape[0])
            keep = spread_over_subjects(list(regs.subjects), n) if args.spread else list(range(n))
            regs = regs.select(keep)
        models: dict[str, Fittable] = {"BLSM-linear": BLSMFittable(model)}
        if args.baseline:
            models["SMPL-reimpl"] = SMPLReimplFittable(load_smpl_reimpl(args.baseline, model))
        for spec in args.also:
            name, sep, path = spec.partition("=")
            if not sep or not name or not path:
                raise ValueError(f"--also {spec}: expected NAME=MODEL.npz")
            models[name] = BLSMFittable(blsm.load(path))
        cfg = EvalConfig(ks=ks, fit=fitcfg, batch=args.batch, pose_generalisation=not args.no_pose)
        for p in write_report(evaluate(models, regs, cfg, args.targets), args.out):
            print(p)
    except ValueError as exc:
        print(f"blsm evaluate: error: {exc}")
        return 2
    return 0


def cmd_train_smpl(args: argparse.Namespace) -> int:
    """``blsm train-smpl``: SMPL-reimpl trained on the training split of a folder of registrations."""
    import blsm
    from blsm.learn.evaluation.fit import FitConfig
    from blsm.learn.evaluation.smpl_reimpl import SMPLTrainConfig, train_smpl_reimpl
    from blsm.learn.registration.registrations import load_registration_set

    try:
        model = blsm.load(args.model)
        regs = load_registration_set(args.registrations, model.num_vertices).split("train")
        iters = tuple(int(i) for i in args.iterations.split(","))
        fit = FitConfig(iterations=iters, lm_iterations=args.lm_iterations)  # type: ignore[arg-type]
        cfg = SMPLTrainConfig(fit=fit)
        smpl = train_smpl_reimpl(model, regs.vertices, args.num_coeffs, regs.subjects, cfg)
        print(smpl.save(args.out))
        print(json.dumps(smpl.meta))
    except ValueError as exc:
        print(f"blsm train-smpl: error: {exc}")
        return 2
    return 0
