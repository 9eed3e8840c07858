"""The generator on fresh samples, as a user's run gets it: time to first image, steady images per
second and the gaps between images, with cold and warm kernel caches, beside the bare path-traced
render of the same kind of fresh scenes.

Every run makes its own part of one large dataset (``generate(part=(I, N))``: shards ``I - 1``,
``I - 1 + N``, ...), so no run renders a sample that an earlier run (or the bare pass) rendered:
a cache keyed by anything of the scene cannot make a run look faster than a real one.

- **cold** (the first ``--workers`` count): the worker processes start with an empty Dr.Jit kernel
  cache (``HOME`` points at a new folder; Dr.Jit keeps compiled kernels in ``$HOME/.drjit``), so
  the first images pay every compile.
- **warm** (every ``--workers`` count): new worker processes on the kernel cache the cold run
  left, a new part.
- Per run: seconds from the call to the first image (worker start-up, subjects loaded, kernels
  compiled or loaded), the steady rate from image ``--warmup`` (at least 3 per worker) to the
  last, and the gaps between consecutive images after the warm-up (median, 90th percentile, max: a
  compile or a stall shows in the max). Shard writing and checksums are included (the main
  process), so is everything a worker does (posing, scene update, path tracing, label pass,
  shadow catcher, labels, encoding).
- **bare**: one process with every core (Dr.Jit's threads), on another part's fresh samples:
  each sample is made, then its path-traced image alone (:func:`synth.render.trace_window` of the
  same scene, window, samples per pixel and seed, the generator's only unavoidable work) is timed
  again. ``bare img/s`` is one over its mean; the ratio ``bare / steady`` is what everything but
  the path tracer costs (1.0: nothing).

    python benchmarks/bench_generate.py [--out docs/benchmarks.md] [--workers 1 2] [--images 120]
        [--variant llvm_ad_rgb] [--subjects DIR/subjects] [--set KEY=VALUE ...] [--json FILE]

Without ``--subjects`` the subjects of the embedded defaults are made first in the work folder
(Anny; not timed). On a GPU machine: ``--variant cuda_ad_rgb --workers 1 4 8 16``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import json
import multiprocessing as mp
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

from report import write_section  # benchmarks/report.py (run as a script)


def _gaps(marks: list[float]) -> dict[str, float]:
    gaps = sorted(b - a for a, b in zip(marks, marks[1:]))
    pick = lambda q: round(1e3 * gaps[min(len(gaps) - 1, int(q * (len(gaps) - 1)))], 1)  # noqa: E731
    return {"gap_ms_p50": pick(0.5), "gap_ms_p90": pick(0.9), "gap_ms_max": round(1e3 * gaps[-1], 1)}


# The run in a process group of its own: `generate` prints each image's time; the benchmark kills
# the whole group when it has seen enough (a pool terminated while its workers are busy on a GPU
# could hang the caller; a killed group cannot).
_CHILD = """
import json, sys, time
from pathlib import Path
from synth.config import GeneratorConfig, from_dict
from synth.generate import generate
cfg = from_dict(GeneratorConfig, json.loads(sys.argv[1]))
print("START", time.time(), flush=True)
generate(cfg, Path(sys.argv[2]), workers=int(sys.argv[3]), progress=False, part=(int(sys.argv[4]), int(sys.argv[5])),
         on_image=lambda n: print("IMG", time.time(), flush=True))
print("DONE", time.time(), flush=True)
"""


def run_generator(cfg, work: Path, subjects: Path, workers: int, part: tuple[int, int], cache_home: Path,
                  warmup: int, max_seconds: float, images: int) -> dict:
    """One ``generate`` run of ``workers`` processes on part ``part`` (in a child process), its
    workers' Dr.Jit cache in ``cache_home``; the images' arrival times."""
    import signal
    import subprocess

    from synth.generate import cfg_json as _cfg_json

    out = work / f"run_w{workers}_part{part[0]}"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    shutil.copytree(subjects, out / "subjects")
    env = dict(os.environ, HOME=str(cache_home))  # read by the workers' Dr.Jit
    t0 = time.time()
    proc = subprocess.Popen([sys.executable, "-c", _CHILD, json.dumps(_cfg_json(cfg)), str(out), str(workers),
                             str(part[0]), str(part[1])], stdout=subprocess.PIPE, text=True, env=env,
                            start_new_session=True)
    marks: list[float] = []
    try:
        for line in proc.stdout:
            if line.startswith("IMG "):
                marks.append(float(line.split()[1]))
                if marks[-1] - marks[0] > max_seconds or len(marks) >= images:
                    break
            elif line.startswith("DONE"):
                break
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    shutil.rmtree(out, ignore_errors=True)
    warm = max(warmup, 3 * workers)
    rec = {"workers": workers, "part": f"{part[0]}/{part[1]}", "images": len(marks)}
    if not marks:
        return rec
    rec["first_image_s"] = round(marks[0] - t0, 2)
    if len(marks) > warm + 2:
        steady = marks[warm - 1:]
        rec["steady_from_image"] = warm
        rec["steady_img_per_s"] = round((len(steady) - 1) / (steady[-1] - steady[0]), 3)
        rec.update(_gaps(steady))
    return rec


def _bare_worker(cfg_dict: dict, dataset: str, first: int, count: int, threads: int, cache_home: str) -> dict:
    """In a process of its own (Dr.Jit reads ``HOME`` when it starts): make samples ``first`` ..
    ``first + count`` and time their path-traced images alone."""
    os.environ["HOME"] = cache_home
    import drjit as dr
    import numpy as np
    import torch

    import synth.render as render
    from synth.config import GeneratorConfig, from_dict
    from synth.sample import SampleMaker
    from synth.dataset.shards import sample_rng

    torch.set_num_threads(1)
    dr.set_thread_count(threads)
    cfg = from_dict(GeneratorConfig, cfg_dict)
    maker = SampleMaker(cfg, Path(dataset), cfg.render.variant, threads)
    calls: list[tuple] = []
    trace = render.trace_window

    def recording(*a):
        calls[:] = [a]
        return trace(*a)

    render.trace_window = recording
    for i in range(first, first + 2):  # warm-up: first compiles, rigs
        maker.make(i, sample_rng(cfg.seed, i))
    for si in range(len(maker.subjects)):
        maker.rig(si)
    sample_t, bare_t, windows = [], [], []
    for i in range(first + 2, first + 2 + count):
        t0 = time.perf_counter()
        maker.make(i, sample_rng(cfg.seed, i))
        sample_t.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        trace(*calls[0])  # the same scene, window, spp and seed; np.asarray waits for the device
        bare_t.append(time.perf_counter() - t0)
        windows.append(calls[0][4][2] * calls[0][4][3])
    return {"threads": threads, "samples": count, "bare_ms": round(1e3 * statistics.fmean(bare_t), 1),
            "bare_img_per_s": round(1.0 / statistics.fmean(bare_t), 3),
            "sample_in_process_ms": round(1e3 * statistics.fmean(sample_t), 1),
            "window_px_mean": round(float(np.mean(windows)))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="docs/benchmarks.md: write the section there")
    ap.add_argument("--json", type=Path, help="also write the records here")
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: a temporary one)")
    ap.add_argument("--subjects", type=Path, help="a subjects/ folder made for this config (default: make them)")
    ap.add_argument("--variant", default="", help="Mitsuba variant (default: the generator's choice)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--images", type=int, default=120, help="images per run at most (a run stops at the first of this and --max-seconds)")
    ap.add_argument("--max-seconds", type=float, default=120.0, help="a run stops this long after its first image")
    ap.add_argument("--warmup", type=int, default=8, help="images before the steady clock starts (at least 3 per worker)")
    ap.add_argument("--bare", type=int, default=16, help="fresh scenes of the bare pass")
    ap.add_argument("--no-cold", action="store_true", help="warm runs only")
    ap.add_argument("--part-offset", type=int, default=0,
                    help="skip this many parts (another invocation's samples, e.g. an A/B against another checkout)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()

    import blsm
    from synth.config import load_config
    from synth.generate import cfg_json as _cfg_json
    from synth.generate import choose_variant, prepare_subjects

    sets = list(args.set) + ([f"render.variant={args.variant}"] if args.variant else [])
    cfg = load_config("-", sets)
    variant = choose_variant(cfg)
    cfg = dataclasses.replace(cfg, render=dataclasses.replace(cfg.render, variant=variant))
    shard = cfg.output.shard_size
    per_part = -(-args.images // shard) * shard
    # Cold for the first worker count (the first run of a fresh machine), warm for every count.
    runs = ([] if args.no_cold else [(args.workers[0], "cold")]) + [(w, "warm") for w in args.workers]
    parts = args.part_offset + len(runs) + 1  # one more for the bare pass
    cfg = dataclasses.replace(cfg, num=per_part * parts)
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_generate_"))
    work.mkdir(parents=True, exist_ok=True)
    subjects = args.subjects
    if subjects is None:
        t0 = time.perf_counter()
        prepare_subjects(cfg, work / "made", blsm.load())
        subjects = work / "made" / "subjects"
        print(f"[bench_generate] subjects made in {time.perf_counter() - t0:.0f} s (not timed below)", flush=True)
    cpus = os.cpu_count() or 1
    print(f"[bench_generate] {cfg.camera.width}x{cfg.camera.height}, {cfg.render.sampler} {cfg.render.spp} spp, hair "
          f"{cfg.hair.enabled}, shadows {cfg.ground.shadows}, people {cfg.people.min}-{cfg.people.max}, {variant}, "
          f"{cpus} cpus", flush=True)
    records = []
    home = None if not args.no_cold else Path(os.environ.get("HOME", work))  # --no-cold: the user's own cache
    for r, (workers, cache) in enumerate(runs):
        if cache == "cold" or home is None:
            home = work / f"home_{r}"
            home.mkdir()
        rec = run_generator(cfg, work, subjects, workers, (args.part_offset + r + 1, parts), home, args.warmup, args.max_seconds,
                            args.images)
        rec.update(kind="generate", cache=cache, kernels_cached=len(list((home / ".drjit").glob("*"))))
        records.append(rec)
        print("[bench_generate] " + json.dumps(rec), flush=True)
    if args.bare <= 0:  # no bare pass (e.g. timing an older checkout, which lacks trace_window)
        if args.json:
            args.json.write_text("".join(json.dumps(r) + "\n" for r in records))
        return 0
    # The bare pass: its own process on the warm cache, another part's fresh samples.
    dataset = work / "bare"
    shutil.rmtree(dataset, ignore_errors=True)
    dataset.mkdir()
    shutil.copytree(subjects, dataset / "subjects")
    first = (parts - 1) * shard  # the last part's first sample (part I holds shards I - 1, I - 1 + N, ...)
    with mp.get_context("spawn").Pool(1) as pool:
        bare = pool.apply(_bare_worker, (_cfg_json(cfg), str(dataset), first, args.bare, cpus, str(home or work)))
    bare["kind"] = "bare"
    records.append(bare)
    print("[bench_generate] " + json.dumps(bare), flush=True)
    if args.json:
        args.json.write_text("".join(json.dumps(r) + "\n" for r in records))
    if args.out:
        gpu = "cuda" in variant
        write_section(args.out, f"generate-{'gpu' if gpu else 'cpu'}", f"Generator on fresh samples ({'GPU' if gpu else 'CPU'})",
                      "benchmarks/bench_generate.py", _report(cfg, variant, records, args, cpus),
                      command=None if not gpu else "`bash benchmarks/gpu_generate.sh` on a lent GPU machine (runs "
                      f"`python benchmarks/bench_generate.py --variant {variant} --workers {' '.join(map(str, args.workers))}"
                      f"{' --no-cold' if args.no_cold else ''} ...`)")
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)
    return 0


def _report(cfg, variant: str, records: list[dict], args, cpus: int) -> list[str]:
    bare = next(r for r in records if r["kind"] == "bare")
    lines = [
        f"{datetime.date.today()}, {platform.node() or 'this machine'} ({cpus} cpus), Mitsuba `{variant}`; the embedded "
        f"defaults{' with ' + ', '.join(args.set) if args.set else ''}: {cfg.camera.width} x {cfg.camera.height} px, "
        f"{cfg.render.sampler} {cfg.render.spp} spp, hair {'on' if cfg.hair.enabled else 'off'}, shadows "
        f"{'on' if cfg.ground.shadows else 'off'}, {cfg.people.min}-{cfg.people.max} people. Every run makes its own "
        "part of one dataset: no sample is rendered twice. Cold: the workers' Dr.Jit kernel cache empty; warm: the cache "
        "the cold run left, new processes. Steady: from image "
        f"{args.warmup} (at least 3 per worker) to the last; gaps between consecutive images after it.",
        "",
        "| workers | kernel cache | images | first image (s) | steady img/s | gap p50 (ms) | gap p90 (ms) | gap max (ms) | bare / steady |",
        "| ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in records:
        if r["kind"] != "generate":
            continue
        rate = r.get("steady_img_per_s")
        ratio = f"{bare['bare_img_per_s'] / rate:.2f}" if rate else "-"
        lines.append(f"| {r['workers']} | {r['cache']} | {r['images']} | {r.get('first_image_s', '-')} | {rate or '-'} | "
                     f"{r.get('gap_ms_p50', '-')} | {r.get('gap_ms_p90', '-')} | {r.get('gap_ms_max', '-')} | {ratio} |")
    lines += [
        "",
        f"Bare path-traced image of {bare['samples']} other fresh scenes, one process with {bare['threads']} threads: "
        f"{bare['bare_ms']} ms ({bare['bare_img_per_s']} img/s; window {bare['window_px_mean']} px on average); the whole "
        f"sample in that process {bare['sample_in_process_ms']} ms.",
    ]
    return lines


if __name__ == "__main__":
    sys.exit(main())
