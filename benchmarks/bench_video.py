"""Sequences against single images at the same settings, on fresh work, as a user's run gets it.

Both runs make ``--frames`` images of ``configs/synth/video.yaml``'s settings (image size, samples
per pixel, people, HDRIs, motion library): one as single images (``sequence.enabled: false``:
each image a new draw of people, poses from the same clips, camera and light), one as
``--frames / T`` sequences of ``T`` frames. Each run is a whole ``synth generate`` in its own
process (worker start-up, subjects loaded, kernels compiled or loaded, shards written), timed from
the call to its end; the subjects (which depend on the seed) are made beforehand for each seed and
copied in (not timed).

- **cold**: a new ``HOME`` for each run, so Dr.Jit's kernel cache (``$HOME/.drjit``) starts empty;
- **warm**: both kinds again, on the kernel caches their cold runs left, with another seed, so no
  run renders a sample an earlier one did. The order alternates (single, sequence, sequence,
  single) so that a drift of the machine does not favour one kind.
- **motion blur**: ``--blur-frames`` frames of sequences with ``sequence.motion_blur`` on (warm).

Then the loader: :class:`synth.dataset.sequences.SequenceDataset` over the warm sequence run's dataset,
clips of 16 frames (stride 8) cropped to 128 px around each person, in ``--loader-workers``
DataLoader workers: clips/s and frames/s of the first pass (fresh worker processes) and a second.

    python benchmarks/bench_video.py [--out docs/benchmarks.md] [--frames 120] [--workers 2] [--set KEY=VALUE]

``make bench`` fixes the people count at 2 (``--set people.min=2 --set people.max=2``): a frame's cost
grows with the people in it, and a sequence draws the count once for all its frames, so with a few
sequences a run the draw, not the generator, would decide the ratio.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from report import write_section  # benchmarks/report.py (run as a script)

ROOT = Path(__file__).resolve().parents[1]


def _generate(config: str, sets: list[str], out: Path, subjects: Path, workers: int, home: Path) -> float:
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    shutil.copytree(subjects, out / "subjects")
    synth = str(Path(sys.executable).with_name("synth"))
    cmd = [synth, "generate", config, "--out", str(out), "--workers", str(workers), *sum((["--set", s] for s in sets), [])]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env=dict(os.environ, HOME=str(home)))
    dt = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)}: exit {r.returncode}\n{r.stderr[-2000:]}")
    return dt


def _loader(dataset: Path, workers: int) -> list[dict]:
    import torch

    from synth.dataset.sequences import SequenceDataset

    ds = SequenceDataset(dataset, clip_len=16, stride=8, mode="person", crop=128, flip_prob=0.5, seed=0)
    out = []
    for rnd in range(2):
        dl = torch.utils.data.DataLoader(ds, batch_size=4, num_workers=workers, shuffle=True,
                                         generator=torch.Generator().manual_seed(rnd))  # fmt: skip
        t0 = time.perf_counter()
        clips = sum(b["images"].shape[0] for b in dl)
        dt = time.perf_counter() - t0
        out.append({"pass": rnd + 1, "clips": clips, "clips_per_s": round(clips / dt, 2),
                    "frames_per_s": round(16 * clips / dt, 1)})  # fmt: skip
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/synth/video.yaml")
    ap.add_argument("--frames", type=int, default=120, help="images per run (a multiple of the config's frames)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--loader-workers", type=int, default=2)
    ap.add_argument("--blur-frames", type=int, default=60, help="frames of the motion-blur run (0: none)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--work", type=Path)
    ap.add_argument("--out", type=Path, help="docs/benchmarks.md: write the section there")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    import blsm
    from synth.config import load_config
    from synth.generate import prepare_subjects

    cfg = load_config(args.config, args.set)
    T = cfg.sequence.frames
    if args.frames % T:
        raise SystemExit(f"--frames {args.frames} is not a multiple of the config's {T} frames a sequence")
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_video_"))
    work.mkdir(parents=True, exist_ok=True)
    # Subjects depend on the seed: made for each seed used (not timed).
    seeds = {"cold": cfg.seed, "warm": cfg.seed + 1000, "blur": cfg.seed + 2000}
    subjects = {}
    for name, seed in seeds.items():
        if name == "blur" and not args.blur_frames:
            continue
        prepare_subjects(dataclasses.replace(cfg, seed=seed), work / f"made_{name}", blsm.load())
        subjects[name] = work / f"made_{name}" / "subjects"
    single = [*args.set, "sequence.enabled=false", f"num={args.frames}"]
    seq = [*args.set, f"num={args.frames // T}"]
    records = []
    order = [("single", "cold"), ("sequence", "cold"), ("sequence", "warm"), ("single", "warm")]
    for r, (kind, cache) in enumerate(order):
        home = work / f"home_{kind}"
        if cache == "cold":
            shutil.rmtree(home, ignore_errors=True)
            home.mkdir()
        sets = (single if kind == "single" else seq) + [f"seed={seeds[cache]}"]  # warm: other samples than cold's
        out = work / f"run_{r}_{kind}_{cache}"
        dt = _generate(args.config, sets, out, subjects[cache], args.workers, home)
        rec = {"kind": kind, "cache": cache, "images": args.frames, "seconds": round(dt, 2),
               "img_per_s": round(args.frames / dt, 3)}  # fmt: skip
        records.append(rec)
        print("[bench_video] " + json.dumps(rec), flush=True)
        if not (kind == "sequence" and cache == "warm"):
            shutil.rmtree(out, ignore_errors=True)
        else:
            loader_data = out
    if args.blur_frames:  # motion blur: warm, its own seed, per frame against the warm sequences
        sets = [*args.set, f"num={args.blur_frames // T}", f"seed={seeds['blur']}", "sequence.motion_blur.enabled=true"]
        dt = _generate(args.config, sets, work / "run_blur", subjects["blur"], args.workers, work / "home_sequence")
        rec = {"kind": "sequence_blur", "cache": "warm", "images": args.blur_frames, "seconds": round(dt, 2),
               "img_per_s": round(args.blur_frames / dt, 3), "subframes": cfg.sequence.motion_blur.subframes}  # fmt: skip
        records.append(rec)
        print("[bench_video] " + json.dumps(rec), flush=True)
        shutil.rmtree(work / "run_blur", ignore_errors=True)
    loader = _loader(loader_data, args.loader_workers)
    for rec in loader:
        print("[bench_video] loader " + json.dumps(rec), flush=True)
    if args.json:
        args.json.write_text(json.dumps({"records": records, "loader": loader}, indent=1) + "\n")
    if args.out:
        cmd = " ".join(["python benchmarks/bench_video.py", *([f"--frames {args.frames}"] if args.frames != 120 else []),
                        *[f"--set {x}" for x in args.set], f"--out {args.out}"])
        write_section(args.out, "video", "Sequences against single images (CPU)", "benchmarks/bench_video.py",
                      _report(cfg, args, records, loader), command=f"`make bench` (runs `{cmd}`)")
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0


def _report(cfg, args, records: list[dict], loader: list[dict]) -> list[str]:
    by = {(r["kind"], r["cache"]): r for r in records}
    lines = [
        f"`{args.config}` settings: {cfg.camera.width}x{cfg.camera.height} px, {cfg.render.sampler} {cfg.render.spp} spp, "
        f"{cfg.people.min}-{cfg.people.max} people, {cfg.background.kind} backgrounds; sequences of "
        f"{cfg.sequence.frames} frames at {cfg.sequence.fps:g} fps (camera paths by the default weights). Each run makes "
        f"{args.frames} new images in a whole `synth generate` ({args.workers} workers, {os.cpu_count()} cpus), "
        "timed from the call to its end (start-up, kernels, shards included; subjects made beforehand)."
        + (f" Overrides: `{' '.join(args.set)}`." if args.set else "")
        + (" The people count is fixed because a frame's cost grows with it and a sequence draws it once for all "
           "its frames: with a few sequences a run, that one draw would decide the ratio." if any(
               k.startswith("people.") for k in args.set) else ""),
        "",
        "| kernel cache | single images img/s | sequence frames/s | sequence / single |",
        "|---|---|---|---|",
    ]
    for cache in ("cold", "warm"):
        a, b = by[("single", cache)], by[("sequence", cache)]
        lines.append(f"| {cache} | {a['img_per_s']:.3f} | {b['img_per_s']:.3f} | {b['img_per_s'] / a['img_per_s']:.2f}x |")
    blur = by.get(("sequence_blur", "warm"))
    if blur:
        warm = by[("sequence", "warm")]
        lines += ["", f"Motion blur ({blur['subframes']} sub-frames, warm cache, {blur['images']} frames): "
                  f"{blur['img_per_s']:.3f} frames/s, {warm['img_per_s'] / blur['img_per_s']:.2f}x the time per frame "
                  "of the sequences without it."]
    lines += ["", f"`SequenceDataset` (person clips of 16 frames, stride 8, 128 px, flips) over the warm sequence run, "
              f"{args.loader_workers} DataLoader workers:", "", "| pass | clips | clips/s | frames/s |", "|---|---|---|---|"]
    lines += [f"| {r['pass']} | {r['clips']} | {r['clips_per_s']} | {r['frames_per_s']} |" for r in loader]
    return lines


if __name__ == "__main__":
    sys.exit(main())
