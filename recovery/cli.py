"""The ``recovery`` command: train, evaluate, predict, cache, export, transfer.

Bad input (a missing or empty dataset, a corrupt checkpoint, one made for another BLSM model file or
config, an unknown config key) is one line ``recovery: error: PATH: problem`` and exit status 2.
"""

from __future__ import annotations

import argparse
import sys

USAGE = """\
recovery train CONFIG --out DIR [--resume]        train (configs/recovery/*.yaml; '-' = defaults)
recovery evaluate CHECKPOINT DATASET --out DIR [--flip]    metrics.json, sheet.png (CHECKPOINT may be 'default')
recovery predict CHECKPOINT PATH --out DIR [--focal F] [--flip] [--min-score S] [--detect-size N]
                 [--detect-passes multi|tiles|single] [--every N] [--max-frames M]
                                                  every person of an image, folder or video (people.json)
recovery predict CHECKPOINT IMAGE --out DIR (--box X0 Y0 X1 Y1 | --whole) [--focal F] [--flip]    one person
recovery cache DATASET --out DIR [--crop N]       pre-crop a dataset for training (train does it itself)
recovery export CHECKPOINT --out FILE [--full]    inference-only copy (float16 unless --full)
recovery transfer CHECKPOINT --real DIR --synthetic DATASET --out DIR    real-photo transfer check (docs/transfer.md;
                                                  CHECKPOINT movenet_lightning / movenet_thunder: MoveNet's own keypoints)
"""


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="recovery", description="HMR-BLSM training, evaluation and prediction",
                                usage=USAGE)
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("config")
    t.add_argument("--out", required=True)
    t.add_argument("--resume", action="store_true", help="continue DIR/last.pt (same config)")
    e = sub.add_parser("evaluate")
    e.add_argument("checkpoint")
    e.add_argument("dataset")
    e.add_argument("--out", required=True)
    e.add_argument("--max-people", type=int, default=0, help="at most N people, spread over the set (0: all)")
    e.add_argument("--batch", type=int, default=32)
    e.add_argument("--flip", action="store_true", help="HMR-BLSM: flip test-time augmentation (average with the mirrored crop)")
    e.add_argument("--no-antialias", action="store_true", help="crop by bilinear sampling alone (as before 2026-12-02)")
    e.add_argument("--fit", type=int, help="HMR-BLSM on MoveNet keypoints: the test-time fit's iterations "
                   "(default: the checkpoint's own; 0: off)")
    pr = sub.add_parser("predict")
    pr.add_argument("checkpoint")
    pr.add_argument("image", metavar="PATH", help="an image, a folder of images or a video")
    pr.add_argument("--out", required=True)
    one = pr.add_mutually_exclusive_group()
    one.add_argument("--box", type=float, nargs=4, metavar=("X0", "Y0", "X1", "Y1"),
                     help="predict this one person of a single image (params.json, mesh.obj, overlay.png)")
    one.add_argument("--whole", action="store_true", help="one person, the whole image padded to a square "
                     "as the crop (predict without --box before the detector)")
    pr.add_argument("--focal", type=float, help="focal length in pixels (default: the image's longer side)")
    pr.add_argument("--flip", action="store_true", help="HMR-BLSM: flip test-time augmentation")
    pr.add_argument("--min-score", type=float, help="the detector's person score threshold (default 0.2; "
                    "0.25 with --detect-passes single)")
    pr.add_argument("--detect-size", type=int,
                    help="each detector pass's input, longer side, pixels (default 256)")
    pr.add_argument("--detect-passes", choices=("multi", "tiles", "single"), default="multi",
                    help="multi (default): MoveNet MultiPose on the whole image and on overlapping tiles, "
                    "merged, each person scored again by MoveNet SinglePose; tiles: the same without that "
                    "second look; single: one pass on the whole image (at most 6 people)")
    pr.add_argument("--every", type=int, default=1, help="videos: every N-th frame")
    pr.add_argument("--max-frames", type=int, default=0, help="videos: at most M frames (0: all)")
    c = sub.add_parser("cache")
    c.add_argument("dataset")
    c.add_argument("--out", required=True)
    c.add_argument("--crop", type=int, default=128)
    c.add_argument("--context", type=float, default=1.5)
    x = sub.add_parser("export")
    x.add_argument("checkpoint")
    x.add_argument("--out", required=True)
    x.add_argument("--full", action="store_true", help="keep float32 weights")
    x.add_argument("--report", help="a metrics.json to embed as the model's summary")
    x.add_argument("--fit", type=int, default=0, help="the test-time fit's iterations its users get by default "
                   "(HMR-BLSM on MoveNet keypoints; 0: none)")
    r = sub.add_parser("transfer", help="real-photo transfer check against a reference 2D pose estimator (docs/transfer.md)")
    r.add_argument("checkpoint", help="a checkpoint, 'default', or movenet_lightning / movenet_thunder (MoveNet's "
                   "own 2D keypoints: the ceiling row)")
    r.add_argument("--real", required=True, help="folder of real images with boxes.json")
    r.add_argument("--synthetic", required=True, help="a synth dataset (the held-out test set)")
    r.add_argument("--out", required=True)
    r.add_argument("--synthetic-people", type=int, default=400, help="at most N synthetic people, spread over the set")
    r.add_argument("--reference-command", help="the reference's command line, run with JOB.json OUT.json appended "
                   "(default: blsm/pose2d/mediapipe_pose.py in .venv-reference)")
    r.add_argument("--sheet", type=int, default=48, help="people on each overlay sheet")
    r.add_argument("--flip", action="store_true", help="HMR-BLSM: flip test-time augmentation")
    r.add_argument("--fit", type=int, help="HMR-BLSM on MoveNet keypoints: the test-time fit's iterations "
                   "(default: the checkpoint's own; 0: off)")
    r.add_argument("--no-antialias", action="store_true", help="crop by bilinear sampling alone, without the "
                   "prefilter of a shrinking crop (the check before 2026-12-02)")
    return p


def error_line(exc: BaseException) -> str:
    """The one-line message of ``exc``. An error raised in a DataLoader worker comes back as torch's
    "Caught ValueError in DataLoader worker process 0." followed by the worker's traceback; its own
    message (which names the shard and sample) is the traceback's last line."""
    lines = [ln for ln in str(exc).splitlines() if ln.strip()]
    if len(lines) > 1 and "DataLoader worker" in lines[0]:
        last, prefix = lines[-1], f"{type(exc).__name__}: "
        return last[len(prefix):] if last.startswith(prefix) else last
    return lines[0] if lines else type(exc).__name__


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        return _run(args)
    except (ValueError, FloatingPointError) as exc:
        print(f"recovery: error: {error_line(exc)}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace) -> int:
    if args.cmd == "train":
        from recovery.config import load_config
        from recovery.train import train

        status = train(load_config(args.config), args.out, resume=args.resume)
        return 130 if status == "interrupted" else 0
    if args.cmd == "evaluate":
        from recovery.eval.evaluate import evaluate, format_report

        if args.max_people < 0 or args.batch < 1:
            raise ValueError("--max-people must be >= 0 and --batch >= 1")
        res = evaluate(args.checkpoint, args.dataset, args.out, batch=args.batch, max_people=args.max_people, flip=args.flip,
                       antialias=not args.no_antialias, fit=args.fit)
        print(format_report(res))
        print(f"wrote {args.out}/metrics.json and {args.out}/sheet.png")
        return 0
    if args.cmd == "predict":
        from pathlib import Path

        from recovery.predict import VIDEO_SUFFIXES, predict, predict_people

        if args.box or args.whole:
            if Path(args.image).is_dir() or Path(args.image).suffix.lower() in VIDEO_SUFFIXES:
                raise ValueError(f"{args.image}: --box and --whole predict one person of a single image")
            predict(args.checkpoint, args.image, args.out, tuple(args.box) if args.box else None, args.focal,
                    flip=args.flip)
            print(f"wrote {args.out}/params.json, mesh.obj, overlay.png")
            return 0
        doc = predict_people(args.checkpoint, args.image, args.out, args.focal, flip=args.flip,
                             min_score=args.min_score, detect_size=args.detect_size, every=args.every,
                             max_frames=args.max_frames, detect_passes=args.detect_passes)
        people = sum(len(e["people"]) for e in doc["images"])
        print(f"wrote {args.out}/people.json: {people} people in {len(doc['images'])} images, "
              f"a mesh per person, an overlay per image")
        return 0
    if args.cmd == "cache":
        from recovery.datasets.cache import build_cache

        build_cache(args.dataset, args.out, args.crop, args.context)
        return 0
    if args.cmd == "export":
        import json
        from pathlib import Path

        from recovery.predictor import export

        summary = json.loads(Path(args.report).read_text()) if args.report else None
        path = export(args.checkpoint, args.out, half=not args.full, summary=summary, fit=args.fit)
        print(f"wrote {path} ({path.stat().st_size / 2**20:.1f} MiB)")
        return 0
    if args.cmd == "transfer":
        from recovery.eval.transfer import format_report, run_transfer

        if args.synthetic_people < 1 or args.sheet < 0:
            raise ValueError("--synthetic-people must be >= 1 and --sheet >= 0")
        rep = run_transfer(args.checkpoint, args.real, args.synthetic, args.out, args.reference_command,
                           args.synthetic_people, flip=args.flip, sheet_count=args.sheet,
                           antialias=not args.no_antialias, fit=args.fit)
        print(format_report(rep))
        print(f"wrote {args.out}/report.json, report.md, sheet_real.png, sheet_synthetic.png")
        return 0
    raise AssertionError(args.cmd)


if __name__ == "__main__":
    sys.exit(main())
