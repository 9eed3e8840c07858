"""The ``synth`` command: generate, preview, validate and export datasets.

    synth generate CONFIG --out DIR [--num N] [--workers W] [--resume [--replace-stale]] [--skip-bad]
                   [--engine local|ray [--address ADDR]] [--part I/N]
    synth merge DIR
    synth preview DIR --out PNG [--count N]
    synth preview DIR --sequence S [--video OUT.gif|OUT.png] [--sheet PNG] [--count N] [--scale K]
    synth validate DIR
    synth export DIR --format spin|coco|sequences --out DIR2 [--overwrite]

Errors in input (a config key, a scan, a folder, an output folder another run is writing, a full
disk) are one line, ``synth: error: ...``, exit status 2; a failed validation exits with status 1.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path


def _generate(args: argparse.Namespace) -> int:
    if sys.stderr.isatty():  # someone is watching: a line before torch, Mitsuba and BLSM load (seconds)
        from synth.progress import log  # light

        log(f"{args.out}: loading the generator and checking "
            f"{'the embedded defaults' if args.config == '-' else args.config}")
    from synth.config import GeneratorConfig, load_config
    from synth.generate import generate

    cfg = load_config(args.config, args.set or ()) if args.config != "-" or args.set else GeneratorConfig()
    if args.num is not None and args.num < 1:
        what = f"sequences of {cfg.sequence.frames} frames" if cfg.sequence.enabled else "images"
        raise ValueError(f"--num: the number of {what} this config makes must be positive, got {args.num}")
    if args.num is not None:
        cfg = dataclasses.replace(cfg, num=args.num)
    if args.skip_bad:
        cfg = dataclasses.replace(cfg, skip_bad=True)
    from synth.dataset.shards import parse_part

    part = parse_part(args.part) if args.part else (1, 1)
    if args.replace_stale and not args.resume:
        raise ValueError("--replace-stale needs --resume")
    if args.address and args.engine != "ray":
        raise ValueError("--address needs --engine ray")
    man = generate(cfg, args.out, workers=args.workers, resume=args.resume, stop_after=args.stop_after, part=part,
                   engine=args.engine, address=args.address, replace_stale=args.replace_stale)
    n = sum(e["samples"] for e in man["shards"].values())
    what = f"part {part[0]}/{part[1]}: " if part[1] > 1 else ""
    print(f"{args.out}: {what}{n} samples in {len(man['shards'])} shards" + (f", {len(man.get('skipped', []))} skipped" if man.get("skipped") else ""))
    if part[1] > 1 and man["complete"]:
        print(f"{args.out}: part {part[0]}/{part[1]} done; when every part is, run: synth merge {args.out}")
    return 0


def _merge(args: argparse.Namespace) -> int:
    from synth.generate import merge

    man = merge(args.dataset)
    n = sum(e["samples"] for e in man["shards"].values())
    print(f"{args.dataset}: merged {n} samples in {len(man['shards'])} shards")
    return 0


def _preview(args: argparse.Namespace) -> int:
    from synth.preview import contact_sheet, sequence_sheet, sequence_video

    if (args.video is not None or args.sheet is not None) != (args.sequence is not None):
        raise ValueError("--video and --sheet need --sequence S, and --sequence needs --video or --sheet")
    if args.out is None and args.video is None and args.sheet is None:
        raise ValueError("preview needs --out PNG, or --sequence S with --video OUT and/or --sheet PNG")
    if args.count < 1 or args.scale < 1:
        raise ValueError(f"--count and --scale must be positive, got {args.count}, {args.scale}")
    if args.out is not None:
        print(contact_sheet(args.dataset, args.out, count=args.count))
    if args.video is not None:
        print(sequence_video(args.dataset, args.sequence, args.video, scale=args.scale))
    if args.sheet is not None:
        print(sequence_sheet(args.dataset, args.sequence, args.sheet, count=args.count, scale=args.scale))
    return 0


def _validate(args: argparse.Namespace) -> int:
    from synth.validate import validate

    rep = validate(args.dataset, log=lambda m: print(f"[validate] {m}", file=sys.stderr, flush=True))
    for f in rep.failures:
        print(f"FAIL {f}")
    print(f"{args.dataset}: {rep.samples} samples checked, {len(rep.failures)} failures")
    return 1 if rep.failures else 0


def _export(args: argparse.Namespace) -> int:
    from synth.export import export

    out = export(args.dataset, args.format, args.out, overwrite=args.overwrite)
    print(out)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="synth", description="Synthetic people with exact labels (BLSM + Mitsuba 3).")
    sub = parser.add_subparsers(dest="command", required=True)
    g = sub.add_parser("generate", help="render a dataset from a config")
    g.add_argument("config", help="configs/synth/*.yaml, or - for the embedded defaults")
    g.add_argument("--out", required=True, type=Path)
    g.add_argument("--num", type=int, help="how many to make (overrides the config's num): images, or sequences "
                   "with a config whose sequence.enabled is true (each of sequence.frames frames)")
    g.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override one config key, VALUE in YAML (repeatable; e.g. --set hair.enabled=false)")
    g.add_argument("--workers", type=int, default=1)
    g.add_argument("--resume", action="store_true", help="continue an interrupted run into --out")
    g.add_argument("--replace-stale", action="store_true",
                   help="with --resume: move a dataset made with other settings to DIR.stale-<time> (nothing is "
                   "deleted) and start anew, instead of refusing")
    g.add_argument("--skip-bad", action="store_true", help="skip and list bad samples or scans instead of stopping")
    g.add_argument("--engine", choices=("local", "ray"), default="local",
                   help="local: a process pool of --workers (default); ray: one Ray task per shard")
    g.add_argument("--address", help="the Ray cluster to join (--engine ray; default: start a local one)")
    g.add_argument("--part", help="make only part I of N of the shards (I/N, e.g. 3/8); join with synth merge")
    g.add_argument("--stop-after", type=int, help=argparse.SUPPRESS)
    g.set_defaults(run=_generate)
    m = sub.add_parser("merge", help="join the parts of a --part I/N run into one dataset")
    m.add_argument("dataset", type=Path)
    m.set_defaults(run=_merge)
    p = sub.add_parser(
        "preview", help="contact sheets with keypoint, mask and part overlays; a sequence's animation"
    )
    p.add_argument("dataset", type=Path)
    p.add_argument("--out", type=Path, help="PNG contact sheet of the first --count samples")
    p.add_argument("--count", type=int, default=8, help="samples of --out, frames of --sheet (default 8)")
    p.add_argument("--sequence", type=int, help="the sequence of --video and --sheet (a sequence dataset)")
    p.add_argument("--video", type=Path, help="animated GIF (.gif) or PNG (.png) of --sequence at its fps")
    p.add_argument("--sheet", type=Path, help="PNG of --count evenly spaced frames of --sequence")
    p.add_argument("--scale", type=int, default=1, help="enlargement of --video and --sheet (default 1)")
    p.set_defaults(run=_preview)
    v = sub.add_parser("validate", help="check every sample; non-zero exit on any failure")
    v.add_argument("dataset", type=Path)
    v.set_defaults(run=_validate)
    e = sub.add_parser("export", help="SPIN/HMR npz, COCO keypoint JSON or one npz per video sequence")
    e.add_argument("dataset", type=Path)
    e.add_argument("--format", required=True, choices=("spin", "coco", "sequences"))
    e.add_argument("--out", required=True, type=Path)
    e.add_argument("--overwrite", action="store_true")
    e.set_defaults(run=_export)
    args = parser.parse_args(argv)
    if getattr(args, "workers", 1) < 1:
        parser.error(f"--workers must be positive, got {args.workers}")
    try:
        return args.run(args)
    except ValueError as exc:
        print(f"synth: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    except RuntimeError as exc:
        print(f"synth: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 1
    except OSError as exc:  # a file that cannot be read or written: still one line naming it
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"synth: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("synth: interrupted; finished shards are kept, continue with --resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
