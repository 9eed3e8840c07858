"""``blsm mocap ...``: import BVH folders into a motion library, preview clips, limit statistics,
and the pose prior. Registered by :func:`blsm.cli.build_parser`."""

from __future__ import annotations

import argparse
import csv
import io
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from blsm.io import atomic_write
from blsm.mocap.bvh import UNITS, read_bvh
from blsm.mocap.library import MotionClip, list_clips, load_clip, save_clip, sha256

_WORKER: dict[str, Any] = {}


def _positive(kind: type):
    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
        if not v > 0:
            raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
        return v

    return parse


def add_parser(sub: Any) -> None:
    p = sub.add_parser("mocap", help="motion capture: import, preview, statistics, pose prior")
    msub = p.add_subparsers(dest="mocap_cmd", required=True)

    imp = msub.add_parser("import", help="retarget a folder of BVH files into a motion library")
    imp.add_argument("src", help="folder of .bvh files")
    imp.add_argument("--out", required=True, help="library folder (one .npz per clip)")
    imp.add_argument("--fps", type=_positive(float), help="resample to this rate (default: keep)")
    imp.add_argument("--map", help="mapping table name or .yaml (default: chosen by joint names)")
    imp.add_argument("--units", default="auto", choices=["auto", *UNITS], help="BVH length unit")
    imp.add_argument("--workers", type=_positive(int), default=min(2, os.cpu_count() or 1))
    imp.add_argument("--overwrite", action="store_true", help="replace clips already in --out")
    imp.add_argument("--clips", nargs="+", metavar="NAME", help="import only these clips (file stems)")
    imp.add_argument("--model", help="model .npz (default: the packaged one)")
    imp.add_argument("--iters", type=_positive(int), default=200, help="Adam iterations per solve")
    imp.set_defaults(func=cmd_import)

    pre = msub.add_parser("preview", help="strip of frames: source skeleton beside the BLSM body")
    pre.add_argument("clip", help="a library clip (.npz)")
    pre.add_argument("--out", required=True, help="PNG to write")
    pre.add_argument("--bvh", help="the source BVH (default: the path recorded in the clip)")
    pre.add_argument("--frames", type=_positive(int), default=8)
    pre.add_argument("--model")
    pre.set_defaults(func=cmd_preview)

    st = msub.add_parser("stats", help="how often each atom sits at its limit (histogram PNG)")
    st.add_argument("library", help="library folder")
    st.add_argument("--out", required=True, help="PNG to write (a .csv is written beside it)")
    st.add_argument("--model")
    st.set_defaults(func=cmd_stats)

    fit = msub.add_parser("fit-prior", help="fit the Gaussian-mixture pose prior on a library")
    fit.add_argument("library", help="library folder")
    fit.add_argument("--out", required=True, help="prior .npz to write")
    fit.add_argument("--k", type=_positive(int), default=12, help="mixture components")
    fit.add_argument("--seed", type=int, default=0)
    fit.add_argument("--exclude", nargs="*", default=[], help="clip names left out of the fit")
    fit.add_argument("--model")
    fit.set_defaults(func=cmd_fit_prior)

    pl = msub.add_parser("plausibility", help="how many prior draws have a backward foot or a limb through the torso")
    pl.add_argument("--prior", help="prior .npz (default: the packaged one)")
    pl.add_argument("--samples", type=_positive(int), default=10000)
    pl.add_argument("--seed", type=int, default=0)
    pl.add_argument("--library", help="also count the real frames of this library folder that the test flags")
    pl.add_argument("--model")
    pl.set_defaults(func=cmd_plausibility)


def _load_model(path: str | None) -> Any:
    import blsm

    return blsm.load(path)


# ------------------------------------------------------------------------------------------------
# import


def _init_worker(model_path: str | None) -> None:
    import torch

    torch.set_num_threads(1)
    _WORKER["model"] = _load_model(model_path)


def _check(job: dict[str, Any]) -> tuple[str, int, str, float] | str:
    """Phase 1: parse and pick the mapping table; a string is an error message."""
    from blsm.mocap.bvh import resample
    from blsm.mocap.retarget import select_map

    try:
        motion = read_bvh(job["path"], units=job["units"])
        smap = select_map(motion, job["map"])
    except ValueError as exc:
        return str(exc)
    frames = motion.num_frames if job["fps"] is None else resample(motion, job["fps"]).num_frames
    return job["path"], frames, smap.name, motion.fps


def _retarget(job: dict[str, Any]) -> dict[str, Any]:
    from blsm.mocap.retarget import retarget, select_map

    t0 = time.perf_counter()
    model = _WORKER["model"]
    motion = read_bvh(job["path"], units=job["units"], fps=job["fps"])
    smap = select_map(motion, job["map"])
    res = retarget(motion, model, smap, first_iters=job["iters"], iters=max(1, job["iters"] // 2))
    return {
        "job": job,
        "res": res,
        "units": motion.units,
        "units_inferred": motion.units_inferred,
        "source_fps": float(job["source_fps"]),
        "fps": float(motion.fps),
        "map": smap.name,
        "root_source": smap.root_source,
        "seconds": time.perf_counter() - t0,
    }


class _Progress:
    """A one-line progress bar on stderr (only on a terminal)."""

    def __init__(self, total: int) -> None:
        self.total, self.done, self.t0 = max(1, total), 0, time.perf_counter()
        self.tty = sys.stderr.isatty()

    def update(self, n: int) -> None:
        self.done += n
        if not self.tty:
            return
        frac = self.done / self.total
        el = time.perf_counter() - self.t0
        eta = el / frac - el if frac > 0 else 0
        bar = "#" * int(30 * frac) + "-" * (30 - int(30 * frac))
        sys.stderr.write(f"\r[{bar}] {self.done}/{self.total} frames, {el:.0f} s, ETA {eta:.0f} s ")
        sys.stderr.flush()

    def close(self) -> None:
        if self.tty:
            sys.stderr.write("\n")


def cmd_import(args: argparse.Namespace) -> int:
    src = Path(args.src)
    if not src.is_dir():
        raise ValueError(f"{src}: not a folder")
    files = sorted(src.glob("*.bvh"))
    if not files:
        raise ValueError(f"{src}: no .bvh files")
    if args.clips:
        missing = sorted(set(args.clips) - {f.stem for f in files})
        if missing:
            raise ValueError(f"{src}: no clip {missing[0]}.bvh")
        files = [f for f in files if f.stem in args.clips]
    out = Path(args.out)
    targets = [out / f"{f.stem}.npz" for f in files]
    exists = [t for t in targets if t.exists()]
    if exists and not args.overwrite:
        raise ValueError(f"{exists[0]}: already exists ({len(exists)} clips in {out}); use --overwrite")
    model = _load_model(args.model)
    jobs = [
        {"path": str(f), "units": args.units, "fps": args.fps, "map": args.map, "iters": args.iters}
        for f in files
    ]
    ctx = multiprocessing.get_context("fork")
    with ProcessPoolExecutor(
        args.workers, mp_context=ctx, initializer=_init_worker, initargs=(args.model,)
    ) as pool:
        # Phase 1: every file parses and has a mapping table, or nothing is written.
        checks = list(pool.map(_check, jobs))
        errors = [c for c in checks if isinstance(c, str)]
        if errors:
            for e in errors[1:]:
                print(f"blsm: error: {e}", file=sys.stderr)
            raise ValueError(errors[0])
        for job, c in zip(jobs, checks, strict=True):
            job["source_fps"] = c[3]  # type: ignore[index]
        total = sum(c[1] for c in checks)  # type: ignore[index]
        print(f"importing {len(jobs)} clips, {total} frames, {args.workers} workers -> {out}")
        bar = _Progress(total)
        rows = []
        all_angles = []
        for r in pool.map(_retarget, jobs):
            res, job = r["res"], r["job"]
            name = Path(job["path"]).stem
            clip = MotionClip(
                name=name,
                fps=r["fps"],
                pose=res.pose,
                global_orient=res.global_orient,
                transl=res.transl,
                dir_err_mean_deg=res.dir_err_mean_deg,
                dir_err_max_deg=res.dir_err_max_deg,
                mpjpe_mm=res.mpjpe_mm,
                segment_err_deg=res.segment_err_deg,
                meta={
                    "source": str(Path(job["path"]).resolve()),
                    "source_sha256": sha256(job["path"]),
                    "source_fps": r["source_fps"],
                    "first_frame": 0,
                    "units": r["units"],
                    "units_inferred": r["units_inferred"],
                    "mapping_table": r["map"],
                    "root_source": r["root_source"],
                    "leg_ratio": res.leg_ratio,
                    "dof_names": model.dof_names,
                    "segments": res.segment_labels,
                    "model": Path(args.model).name if args.model else "blsm_anny_v1.npz",
                },
            )
            save_clip(clip, out / f"{name}.npz")
            all_angles.append(res.angles)
            worst = int(np.argmax(res.segment_err_deg.mean(0)))
            row = {
                "clip": name,
                "frames": clip.num_frames,
                "fps": round(clip.fps, 3),
                "mpjpe_median_mm": float(np.median(res.mpjpe_mm)),
                "mpjpe_mean_mm": float(res.mpjpe_mm.mean()),
                "mpjpe_max_mm": float(res.mpjpe_mm.max()),
                "dir_err_mean_deg": float(res.dir_err_mean_deg.mean()),
                "dir_err_max_deg": float(res.dir_err_max_deg.max()),
                "worst_segment": res.segment_labels[worst],
                "seconds": round(r["seconds"], 1),
            }
            rows.append(row)
            bar.update(clip.num_frames)
            if bar.tty:
                sys.stderr.write("\r" + " " * 79 + "\r")
            print(
                f"{name:>12s}  {row['frames']:5d} fr  MPJPE med {row['mpjpe_median_mm']:5.1f} "
                f"max {row['mpjpe_max_mm']:6.1f} mm  dir {row['dir_err_mean_deg']:4.1f} deg "
                f"(max {row['dir_err_max_deg']:5.1f}, worst {row['worst_segment']})  {row['seconds']:.0f} s",
                flush=True,
            )
        bar.close()
    _write_csv(out / "summary.csv", rows)
    _print_summary(rows)
    _write_limit_stats(np.concatenate(all_angles), model, out / "limit_hits.png")
    return 0


def _write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]))
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{v:.2f}" if isinstance(v, float) else v) for k, v in r.items()})
    with atomic_write(path, "w") as f:
        f.write(buf.getvalue())


def _print_summary(rows: list[dict[str, Any]]) -> None:
    med = np.array([r["mpjpe_median_mm"] for r in rows])
    dirs = np.array([r["dir_err_mean_deg"] for r in rows])
    frames = sum(r["frames"] for r in rows)
    print()
    print(f"{'clips':>28s}: {len(rows)} ({frames} frames)")
    worst = max(r["dir_err_max_deg"] for r in rows)
    print(
        f"{'median per-clip MPJPE':>28s}: {np.median(med):.1f} mm  "
        f"(per-clip medians {med.min():.1f} .. {med.max():.1f} mm; target <= 40)"
    )
    print(
        f"{'bone-direction error':>28s}: mean {np.mean(dirs):.1f} deg, "
        f"median of clip means {np.median(dirs):.1f} deg, worst frame {worst:.1f} deg"
    )


def _write_limit_stats(angles: np.ndarray, model: Any, png: Path) -> None:
    from blsm.mocap.stats import limit_hits, plot_limit_hits

    hits = limit_hits(angles, model.dof_limits.double().numpy(), model.dof_names)
    plot_limit_hits(hits, png)
    rows = [
        {"atom": n, "at_min": float(lo), "at_max": float(hi)}
        for n, lo, hi in zip(hits.names, hits.lower, hits.upper, strict=True)
    ]
    _write_csv(png.with_suffix(".csv"), rows)
    flagged = hits.flagged()
    print(f"{'limit hits':>28s}: {png} ({len(flagged)} atoms pinned in > 5 % of frames)")
    for name, side, frac in flagged:
        print(f"{'':>30s}{name} at {side} in {frac:.0%} of frames")


# ------------------------------------------------------------------------------------------------
# preview, stats, prior


def cmd_preview(args: argparse.Namespace) -> int:
    from blsm.mocap.preview import render_preview

    clip = load_clip(args.clip)
    model = _load_model(args.model)
    path = render_preview(clip, model, args.out, bvh=args.bvh, frames=args.frames)
    print(f"wrote {path}")
    return 0


def _library(folder: str, model: Any, exclude: list[str] = ()) -> tuple[list[MotionClip], np.ndarray]:
    """The clips of a library folder minus ``exclude``, and their stacked poses (N, 47) float64."""
    clips = [load_clip(p) for p in list_clips(folder)]
    unknown = set(exclude) - {c.name for c in clips}
    if unknown:
        raise ValueError(f"{folder}: no clip named {sorted(unknown)[0]!r} to exclude")
    for c in clips:
        if c.meta.get("dof_names") != model.dof_names:
            raise ValueError(f"{c.path}: its atoms differ from the model's (imported with another model?)")
    used = [c for c in clips if c.name not in exclude]
    return used, np.concatenate([c.pose for c in used]).astype(np.float64)


def cmd_stats(args: argparse.Namespace) -> int:
    import torch

    from blsm.joint_limits import angles_from_unconstrained

    model = _load_model(args.model)
    _, x = _library(args.library, model)
    angles = angles_from_unconstrained(torch.as_tensor(x), model.dof_limits.double()).numpy()
    _write_limit_stats(angles, model, Path(args.out))
    return 0


def cmd_plausibility(args: argparse.Namespace) -> int:
    """Draw ``--samples`` poses from the prior, count the implausible ones (blsm.mocap.plausible),
    re-draw those as ``synth generate`` does and check the result again."""
    import torch

    from blsm.mocap.plausible import PoseChecker
    from blsm.mocap.prior import DEFAULT_PRIOR, load_prior

    model = _load_model(args.model)
    path = args.prior or DEFAULT_PRIOR
    prior = load_prior(path)
    checker = PoseChecker(model)
    g = torch.Generator().manual_seed(args.seed)
    x = prior.sample(args.samples, g)
    first = checker.check(x)
    feet, limbs, ok = first.foot_backwards.sum(0), int(first.limb_in_torso.sum()), first.plausible
    n_bad = int((~ok).sum())
    print(f"prior {path}: {args.samples} draws (seed {args.seed}) on the mean body")
    behind = first.toes_behind_heel.sum(0)
    print(f"  toes behind the heel as posed (left / right; not a test): {behind[0]} / {behind[1]}")
    print(f"  foot backwards, leg straightened (left / right): {feet[0]} / {feet[1]}; limb through the torso: {limbs}")
    print(f"  rejected: {n_bad} of {args.samples} ({100.0 * n_bad / args.samples:.2f} %)")
    draws = 0
    while not ok.all():
        bad = torch.from_numpy(~ok).nonzero().squeeze(1)
        y = prior.sample(len(bad), g)
        draws += len(bad)
        good = torch.from_numpy(checker.check(y).plausible)
        x[bad[good]] = y[good]
        ok[bad[good].numpy()] = True
    final = checker.check(x)
    print(f"  after re-drawing ({draws} more draws): foot backwards {int(final.foot_backwards.sum())}, "
          f"limb through the torso {int(final.limb_in_torso.sum())}")
    if args.library:
        _, lib = _library(args.library, model)
        real = checker.check(torch.as_tensor(lib, dtype=torch.float32))
        print(f"library {args.library}: {len(lib)} real frames; toes behind the heel as posed "
              f"{int(real.toes_behind_heel.any(1).sum())}; flagged although real: foot backwards "
              f"{int(real.foot_backwards.any(1).sum())}, limb through the torso {int(real.limb_in_torso.sum())}")
    return 0


def cmd_fit_prior(args: argparse.Namespace) -> int:
    from blsm.mocap.prior import fit_pose_prior

    model = _load_model(args.model)
    used, x = _library(args.library, model, args.exclude)
    t0 = time.perf_counter()
    prior = fit_pose_prior(
        x,
        model.dof_limits.double(),
        model.dof_names,
        k=args.k,
        seed=args.seed,
        meta={
            "clips": [c.name for c in used],
            "excluded": list(args.exclude),
            "frames": int(x.shape[0]),
            "fps": sorted({round(c.fps, 3) for c in used}),
            "k": args.k,
            "seed": args.seed,
            "command": "blsm mocap fit-prior",
        },
    )
    prior.save(args.out)
    dt = time.perf_counter() - t0
    print(f"fitted {args.k} components on {x.shape[0]} frames of {len(used)} clips in {dt:.1f} s")
    print(f"wrote {args.out}")
    return 0
