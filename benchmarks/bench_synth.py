"""``synth generate`` throughput against bare ``mi.render`` of the same scene, and worker memory.

Bare: one process loads the generator's scene (a ``SampleMaker``, as a worker does), makes a few
samples so the scene holds a person, then renders that scene with its image sensor at the config's
spp again and again (``mi.render`` converted to numpy, so it waits for the result), with Dr.Jit
using every core. Its images per second is the ceiling for the machine.

End to end: ``synth.generate.generate`` with ``--workers`` processes (the cores split between
them, as ``synth generate`` does) on the same config: posing, scene updates, the path-traced image,
the pixel-centre label pass, every label, encoding, shard writing and checksums. Its images per
second is taken between image ``--warmup`` and the last image (subjects are made beforehand and
worker start-up is excluded; both are once per run). The ratio is bare / end to end images per
second: 1.0 would mean labels and I/O cost nothing.

Memory: the resident set size of every worker process (``/proc``), read when the run reaches image
100 and at its last image (``--images``, 2000 by default). Workers are not recycled during the run.

    python benchmarks/bench_synth.py [--out docs/benchmarks.md] [--images 2000] [--workers 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from report import write_section  # benchmarks/report.py (run as a script)


def _rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def _worker_rss() -> dict[int, float]:
    """RSS (MiB) by pid of this process's pool workers (the children that hold a generator, i.e.
    more than 200 MiB; the multiprocessing resource tracker is left out)."""
    rss = {}
    for c in _children(os.getpid()):
        try:
            r = _rss_mib(c)
        except OSError:
            continue
        if r > 200:
            rss[c] = r
    return rss


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="write the section into this markdown file")
    parser.add_argument("--images", type=int, default=2000, help="images of the end-to-end run")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--warmup", type=int, default=20, help="images before the end-to-end clock starts")
    parser.add_argument("--bare", type=int, default=40, help="bare renders timed")
    parser.add_argument("--subjects", type=int, default=8)
    args = parser.parse_args()

    import drjit as dr
    import mitsuba
    import torch

    import blsm
    from synth.config import GeneratorConfig, OutputConfig, RenderConfig, SubjectsConfig
    from synth.generate import SampleMaker, choose_variant, generate, prepare_subjects
    from synth.shards import sample_rng

    base = GeneratorConfig()
    cfg = dataclasses.replace(
        base,
        num=args.images,
        subjects=SubjectsConfig(count=args.subjects),
        render=dataclasses.replace(base.render, recycle_after=args.images + 1),
        output=OutputConfig(shard_size=256),
    )
    cam, spp = cfg.camera, cfg.render.spp
    variant = choose_variant(cfg)
    cores = os.cpu_count() or 1
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "dataset"
        print(f"[bench] preparing {args.subjects} subjects (not timed)", file=sys.stderr, flush=True)
        prepare_subjects(cfg, out, blsm.load())

        # Bare mi.render of the generator's scene, all cores.
        torch.set_num_threads(1)
        dr.set_thread_count(cores)
        maker = SampleMaker(cfg, out, variant)
        for i in range(4):
            maker.make(i, sample_rng(cfg.seed, i))
        r = next(iter(maker._renderers.values()))
        mi, sensor = r.mi, r.scene.sensors()[0]
        bare = []
        for k in range(args.bare):
            t0 = time.perf_counter()
            np.asarray(mi.TensorXf(mi.render(r.scene, sensor=sensor, spp=spp, seed=k)))
            bare.append(time.perf_counter() - t0)
        t_bare = statistics.median(bare)
        del maker, r
        print(f"[bench] bare mi.render: {t_bare * 1e3:.0f} ms ({1 / t_bare:.2f} img/s)", file=sys.stderr, flush=True)

        # End to end with worker processes.
        marks: dict[int, float] = {}
        rss: dict[int, list[float]] = {}
        mem_at = (100, args.images)

        def on_image(n: int) -> None:
            marks[n] = time.perf_counter()
            if n in mem_at:
                rss[n] = _worker_rss()

        t0 = time.perf_counter()
        generate(cfg, out, workers=args.workers, progress=True, on_image=on_image)
        wall = time.perf_counter() - t0
    n_timed = args.images - args.warmup
    e2e_rate = n_timed / (marks[args.images] - marks[args.warmup])
    ratio = (1 / t_bare) / e2e_rate
    if set(rss[mem_at[0]]) != set(rss[mem_at[1]]):
        raise RuntimeError(f"workers changed during the run: {rss}")
    pids = sorted(rss[mem_at[0]])
    first, last = [rss[mem_at[0]][p] for p in pids], [rss[mem_at[1]][p] for p in pids]
    growth = max(b / a for a, b in zip(first, last))
    print(f"[bench] end to end: {e2e_rate:.2f} img/s ({args.workers} workers), bare {1 / t_bare:.2f} img/s, "
          f"ratio {ratio:.2f}; wall {wall:.0f} s", file=sys.stderr)
    print(f"[bench] worker RSS at image {mem_at[0]}: {[round(x) for x in first]} MiB, at image {mem_at[1]}: "
          f"{[round(x) for x in last]} MiB (largest growth {growth:.3f}x)", file=sys.stderr)
    if args.out is not None:
        fmt_rss = lambda xs: ", ".join(f"{x:.0f}" for x in xs)  # noqa: E731
        lines = [
            f"Measured {datetime.date.today().isoformat()} on {platform.machine()}, {cores} cores, Mitsuba "
            f"{mitsuba.__version__} `{variant}`. The embedded default config: {cam.width} x {cam.height}, "
            f"{spp} spp, max depth {cfg.render.max_depth}, procedural sky, {args.subjects} Anny subjects "
            f"(~13k vertices, {cfg.subjects.texture_size}² textures), rigged pipeline, poses from the prior, "
            "every label on (mask, parts, bones, depth EXR, correspondences, keypoints with visibility, "
            "boxes, BLSM parameters), shards and checksums written.",
            "",
            "| | images / s | ms / image |",
            "| --- | ---: | ---: |",
            f"| bare `mi.render` of the generator's scene, same sensor and spp, {cores} threads "
            f"(median of {args.bare}) | {1 / t_bare:.2f} | {t_bare * 1e3:.0f} |",
            f"| `synth generate`, {args.workers} workers, images {args.warmup}–{args.images} "
            f"| {e2e_rate:.2f} | {1e3 / e2e_rate:.0f} |",
            f"| **ratio bare / end to end** | **{ratio:.2f}** (target ≤ 1.5) | |",
            "",
            f"The whole run of {args.images} images took {wall / 60:.1f} minutes including worker start-up.",
            "",
            "Resident memory of each worker process (MiB; workers not recycled during the run):",
            "",
            "| image | RSS of each worker (MiB) |",
            "| ---: | --- |",
            f"| {mem_at[0]} | {fmt_rss(first)} |",
            f"| {mem_at[1]} | {fmt_rss(last)} |",
            "",
            f"Largest growth of a worker from image {mem_at[0]} to image {mem_at[1]}: **{growth:.3f}×** "
            "(target: flat).",
            "",
        ]
        write_section(args.out, "synth", "Generator: `synth generate` vs bare `mi.render` (CPU), and memory", "benchmarks/bench_synth.py", lines)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
