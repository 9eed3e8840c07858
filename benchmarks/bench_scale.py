"""``synth generate --engine ray`` on a local two-node Ray cluster against ``--workers 2``.

Both make the same dataset (the config below: 128 px, 8 spp, 1-2 people, the procedural sky), from
the same subjects (made once beforehand and copied: both engines make them once per dataset in the
driver). Rounds alternate local, Ray, local, Ray, ...; each times ``generate`` end to end, worker
start-up included (the local pool's two spawned processes; for Ray, the driver's connection and its
worker processes, started on its first tasks: each Ray round connects a driver of its own, as a
``synth generate --address`` run does, so no warm worker carries over between rounds). The Ray cluster (``ray.cluster_utils.Cluster``: a head and one more node, 1 CPU each)
is started once and is not timed: on a cluster it outlives the runs.

Per-task overhead: the mean round trip of an empty Ray task on the same cluster (200 of them, after
a warm-up), and, from the timed runs, (Ray time - local time) / shards.

Ray binds the host's address unless it is alone with loopback, so the script re-runs itself inside
``unshare -n`` (a network namespace with only ``lo``); it needs root (CI has it).

    python benchmarks/bench_scale.py [--out docs/benchmarks.md] [--images 600] [--shard-size 20] [--rounds 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CONFIG = """seed: 11
subjects: {count: 2, texture_size: 256}
people: {min: 1, max: 2}
camera: {width: 128, height: 128}
background: {env_width: 256}
render: {spp: 8}
"""


def _inside(args: argparse.Namespace) -> None:
    import logging

    import ray
    from ray.cluster_utils import Cluster

    sys.path.insert(0, str(Path(__file__).parent))
    from report import write_section

    from synth.config import load_config
    from synth.generate import generate

    tmp = Path(tempfile.mkdtemp(prefix="bench_scale_"))
    cfg_path = tmp / "cfg.yaml"
    cfg_path.write_text(CONFIG + f"num: {args.images}\noutput: {{shard_size: {args.shard_size}}}\n")
    cfg = load_config(cfg_path)
    shards = -(-args.images // args.shard_size)
    print(f"[bench] subjects for {cfg_path}", file=sys.stderr, flush=True)
    subjects = tmp / "subjects_run"
    generate(dataclasses.replace(cfg, num=1), subjects, progress=False)

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    ray.init(address=cluster.address, log_to_driver=False, logging_level=logging.ERROR)

    @ray.remote(num_cpus=1)
    def empty() -> None:
        return None

    ray.get([empty.remote() for _ in range(20)])
    t0 = time.perf_counter()
    for _ in range(200):
        ray.get(empty.remote())
    trip_ms = (time.perf_counter() - t0) / 200 * 1e3
    ray.shutdown()

    times: dict[str, list[float]] = {"local": [], "ray": []}
    firsts: dict[str, list[float]] = {"local": [], "ray": []}  # seconds to the first image
    for r in range(args.rounds):
        for engine in ("local", "ray"):
            out = tmp / f"{engine}_{r}"
            out.mkdir()
            shutil.copytree(subjects / "subjects", out / "subjects")
            t0 = time.perf_counter()
            if engine == "ray":  # a driver of its own, as a `synth generate --address` run: fresh workers
                ray.init(address=cluster.address, log_to_driver=False, logging_level=logging.ERROR)

            def first_image(made: int, engine: str = engine, t0: float = t0, r: int = r) -> None:
                if made >= 1 and len(firsts[engine]) == r:
                    firsts[engine].append(time.perf_counter() - t0)

            generate(cfg, out, workers=2, engine=engine, progress=False, on_image=first_image)
            if engine == "ray":
                ray.shutdown()
            times[engine].append(time.perf_counter() - t0)
            print(f"[bench] round {r + 1} {engine}: {args.images / times[engine][-1]:.2f} images/s", file=sys.stderr, flush=True)
            first = tmp / "local_0"
            if out != first:  # the engines make the same dataset
                differ = [p.name for p in first.glob("shard-*.tar") if (out / p.name).read_bytes() != p.read_bytes()]
                print(f"[bench] {out.name} vs local_0: {len(differ)} shards differ {differ}", file=sys.stderr)
                shutil.rmtree(out)
    cluster.shutdown()
    shutil.rmtree(tmp, ignore_errors=True)

    loc, ray_t = statistics.median(times["local"]), statistics.median(times["ray"])
    steady = {e: statistics.median((args.images - 1) / (t - f) for t, f in zip(times[e], firsts[e], strict=True))
              for e in times}
    ratio = loc / ray_t
    per_task = (ray_t - loc) / shards * 1e3
    import torch

    lines = [
        f"Measured {datetime.date.today()} on {platform.machine()}, {os.cpu_count()} cores, Ray {ray.__version__}, "
        f"torch {torch.__version__}: {args.images} images at 128 px, 8 spp, 1-2 people, procedural sky, "
        f"{shards} shards of {args.shard_size}; median of {args.rounds} alternating rounds, end to end with worker "
        "start-up (subjects made beforehand; the Ray cluster started once, untimed).",
        "",
        "| engine | images / s | ratio |",
        "| --- | ---: | ---: |",
        f"| `--workers 2` (local process pool) | {args.images / loc:.2f} | |",
        f"| `--engine ray`, 2 local nodes of 1 CPU (`ray.cluster_utils.Cluster`) | {args.images / ray_t:.2f} | "
        f"**{ratio:.2f}** (target >= 0.9) |",
        "",
        f"Rounds (s): local {', '.join(f'{t:.1f}' for t in times['local'])}; "
        f"Ray {', '.join(f'{t:.1f}' for t in times['ray'])}. Start-up, to the first image (median): local "
        f"{statistics.median(firsts['local']):.1f} s, Ray {statistics.median(firsts['ray']):.1f} s (Ray's worker "
        f"processes boot Ray before importing the generator); after it, local {steady['local']:.2f} and Ray "
        f"{steady['ray']:.2f} images/s (ratio {steady['ray'] / steady['local']:.2f}).",
        f"Per-task overhead: an empty task's round trip {trip_ms:.1f} ms; (Ray - local) / shards = {per_task:+.0f} ms "
        f"per shard of {args.shard_size} images, start-up included.",
    ]
    write_section(Path(args.out), "scale", "Generator on a Ray cluster vs the local pool (CPU)",
                  "benchmarks/bench_scale.py", lines)
    print("\n".join(lines))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="docs/benchmarks.md")
    p.add_argument("--images", type=int, default=600)
    p.add_argument("--shard-size", type=int, default=20)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--inside", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.inside:
        _inside(args)
        return
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0",
           "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parents[1]), os.environ.get("PYTHONPATH", "")])}
    argv = " ".join([sys.executable, str(Path(__file__).resolve()), *sys.argv[1:], "--inside"])
    r = subprocess.run(["unshare", "-n", "sh", "-c", f"ip link set lo up && exec {argv}"], env=env)
    sys.exit(r.returncode)


if __name__ == "__main__":
    main()
