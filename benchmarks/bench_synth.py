"""``synth generate`` throughput against bare ``mi.render`` of the same scene, and worker memory.

Bare: one process loads the generator's scene (a ``SampleMaker``, as a worker does); for each of
``--bare`` samples it makes the sample (person, camera, sky) and then renders that same scene again
with its image sensor at the config's spp (``mi.render`` converted to numpy, so it waits for the
result; one untimed render first, so that caches are warm), with Dr.Jit using every core. The mean
over these scenes is the bare time: a render's cost depends on how much of the image the person
covers, so one scene alone is not representative. Three bare times are taken over the same scenes:

- as in a worker: the generator's scene (each person a shape group seen through an instance) with
  the renderer's spare emitter alive (see ``synth.render.PeopleRenderer``); the headline ratio;
- alone: the same scene with no second emitter alive in the process, as ``mi.render`` renders it
  in a process of its own;
- plain: the same scenes with the meshes directly in the scene (no shape groups).

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
import gc
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
    from synth.config import GeneratorConfig, OutputConfig, SubjectsConfig
    from synth.generate import choose_variant, generate, prepare_subjects
    from synth.render import PeopleRenderer
    from synth.sample import SampleMaker
    from synth.dataset.shards import sample_rng

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

        # Bare mi.render of the generator's scenes, all cores.
        torch.set_num_threads(1)
        dr.set_thread_count(cores)
        # Every render the generator asks for is recorded, so that the same scene can be loaded in
        # a second renderer with the plain layout (meshes directly in the scene, no instances).
        calls: list[tuple] = []
        render = PeopleRenderer.render

        def recording(self, *a, **kw):
            calls[:] = [(self, a, kw)]
            return render(self, *a, **kw)

        def bare_render(rr, k: int) -> float:
            mi, sensor = rr.mi, rr.scene.sensors()[0]
            # One untimed render first: the first render after the generator's other work (labels,
            # encoding) is up to a third slower than the ones after it (caches), and the bare time
            # is meant to be mi.render's own cost.
            np.asarray(mi.TensorXf(mi.render(rr.scene, sensor=sensor, spp=spp, seed=k)))
            t0 = time.perf_counter()
            np.asarray(mi.TensorXf(mi.render(rr.scene, sensor=sensor, spp=spp, seed=k)))
            return time.perf_counter() - t0

        PeopleRenderer.render = recording
        try:
            maker = SampleMaker(cfg, out, variant)
            maker.make(0, sample_rng(cfg.seed, 0))  # compiles the kernels
            # (1) As in a worker: the generator's scene (shape groups) and its spare emitter.
            # (2) The same scenes with the plain layout, in a second renderer.
            # (3) The generator's scene with no second emitter alive: mi.render as Mitsuba renders
            #     the scene in a process of its own.
            bare: dict[str, list[float]] = {"worker": [], "plain": [], "alone": []}
            update: dict[str, list[float]] = {"worker": [], "plain": []}
            r = calls[0][0]
            spare, r.spare_emitter = r.spare_emitter, None
            del spare
            gc.collect()
            for k in range(args.bare):
                maker.make(k, sample_rng(cfg.seed, k))
                bare["alone"].append(bare_render(calls[0][0], k))
            r.spare_emitter = r.mi.load_dict({"type": "constant"})
            plain = None
            for k in range(args.bare):
                # The scene of sample k (the person, camera and sky the generator made), rendered
                # again: the time depends on how much of the image the person covers, so it is
                # averaged over as many generated scenes as there are timed renders.
                maker.make(k, sample_rng(cfg.seed, k))
                r, a, kw = calls[0]
                if plain is None:
                    plain = PeopleRenderer(
                        r.meshes, [t.shape[:2] for t in a[1]], r.width, r.height, env_shape=a[3].shape[:2],
                        variant=r.variant, max_depth=cfg.render.max_depth, backplate=r.backplate, instanced=False,
                    )  # fmt: skip
                render(plain, *a, **kw)
                for name, rr in (("worker", r), ("plain", plain)):
                    bare[name].append(bare_render(rr, k))
                    t0 = time.perf_counter()
                    rr._textures.clear()  # the update of a new image: the texture too
                    rr._assign(*a[:6])  # the per-image scene update: vertices (BVH), texture, sky, camera
                    update[name].append(time.perf_counter() - t0)
            del plain
        finally:
            PeopleRenderer.render = render
        calls.clear()
        t_bare = {name: statistics.fmean(v) for name, v in bare.items()}
        t_upd = {name: statistics.fmean(v) for name, v in update.items()}
        del maker, r
        print(f"[bench] bare mi.render (ms): {', '.join(f'{n} {t * 1e3:.0f}' for n, t in t_bare.items())}; "
              f"scene update (ms): {', '.join(f'{n} {t * 1e3:.0f}' for n, t in t_upd.items())}",
              file=sys.stderr, flush=True)

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
    ratios = {name: (1 / t) / e2e_rate for name, t in t_bare.items()}
    ratio = ratios["worker"]
    if set(rss[mem_at[0]]) != set(rss[mem_at[1]]):
        raise RuntimeError(f"workers changed during the run: {rss}")
    pids = sorted(rss[mem_at[0]])
    first, last = [rss[mem_at[0]][p] for p in pids], [rss[mem_at[1]][p] for p in pids]
    growth = max(b / a for a, b in zip(first, last))
    print(f"[bench] end to end: {e2e_rate:.2f} img/s ({args.workers} workers), bare {1 / t_bare['worker']:.2f} img/s, "
          f"ratio {ratio:.2f} ({', '.join(f'{n} {x:.2f}' for n, x in ratios.items())}); wall {wall:.0f} s", file=sys.stderr)
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
            f"Bare `mi.render`: the generator's scenes rendered again with the same sensor and spp, {cores} "
            f"threads, mean over {args.bare} generated scenes. The ratio is bare / end-to-end images per second.",
            "",
            "| | images / s | ms / image | ratio |",
            "| --- | ---: | ---: | ---: |",
            f"| `synth generate`, {args.workers} workers, images {args.warmup}–{args.images} "
            f"| {e2e_rate:.2f} | {1e3 / e2e_rate:.0f} | |",
            f"| **bare, as in a worker** (shape groups, spare emitter alive) | {1 / t_bare['worker']:.2f} "
            f"| {t_bare['worker'] * 1e3:.0f} | **{ratios['worker']:.2f}** (target ≤ 1.5) |",
            f"| bare, the same scene alone in its process (no second emitter) | {1 / t_bare['alone']:.2f} "
            f"| {t_bare['alone'] * 1e3:.0f} | {ratios['alone']:.2f} |",
            f"| bare, meshes directly in the scene (no shape groups) | {1 / t_bare['plain']:.2f} "
            f"| {t_bare['plain'] * 1e3:.0f} | {ratios['plain']:.2f} |",
            "",
            f"Per-image scene update (vertices and BVH, normals, texture, sky, camera), {cores} threads: "
            f"{t_upd['worker'] * 1e3:.1f} ms with shape groups, {t_upd['plain'] * 1e3:.1f} ms with the meshes directly "
            "in the scene.",
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
