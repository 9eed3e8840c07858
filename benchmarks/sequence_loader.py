"""Made no file: the loader check of docs/video.md, "Throughput" (issue 31, 2026-11-26, f97d348).

Throughput of :class:`synth.dataset.sequences.SequenceDataset` through a ``DataLoader``: clips/s and
frames/s on a dataset folder. ``make bench`` measures the loader on its own dataset
(benchmarks/bench_video.py, docs/benchmarks.md); this takes any dataset and more options.

Each pass starts fresh workers (a new ``DataLoader``, ``persistent_workers=False``) over the same
``--clips`` clips (a seeded random subset, so reads are not sequential). The first pass is *cold*
(the first reads of these shards' bytes by this process; the OS page cache may still hold them from
an earlier run: drop it, as root, with ``sync; echo 3 > /proc/sys/vm/drop_caches``, for a truly
cold disk), the later ones *warm*. For each pass: the time to the first batch (worker start-up and
the first clips), and the rate over the whole pass and after the first batch (steady state).
Building the dataset (the index and, in person mode, every frame's JSON) is timed apart.

    python benchmarks/sequence_loader.py DATASET [--mode person|frame] [--clip-len 16] [--stride 8]
        [--crop 224] [--batch-size 8] [--workers 8] [--clips 512] [--passes 2] [--flip-prob 0.5]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, Subset

from synth.dataset.sequences import MODES, SequenceDataset


def measure(ds: torch.utils.data.Dataset, batch_size: int, workers: int) -> dict[str, float]:
    """One pass over ``ds`` with fresh workers: seconds to the first batch, clips, frames and the
    clips/s and frames/s over the pass and after the first batch."""
    loader = DataLoader(
        ds, batch_size=batch_size, num_workers=workers, shuffle=False, persistent_workers=False
    )
    start = time.perf_counter()
    first = clips = frames = 0.0
    after = (0.0, 0.0)
    for b in loader:
        n, length = b["images"].shape[:2]
        clips, frames = clips + n, frames + n * length
        if not first:
            first = time.perf_counter() - start
            after = (clips, frames)
    total = time.perf_counter() - start
    steady = max(total - first, 1e-9)
    return {
        "first_batch_s": first,
        "total_s": total,
        "clips": clips,
        "frames": frames,
        "clips_per_s": clips / total,
        "frames_per_s": frames / total,
        "steady_clips_per_s": (clips - after[0]) / steady if clips > after[0] else float("nan"),
        "steady_frames_per_s": (frames - after[1]) / steady if clips > after[0] else float("nan"),
    }


def report(label: str, r: dict[str, Any]) -> str:
    return (
        f"{label}: {r['clips']:.0f} clips ({r['frames']:.0f} frames) in {r['total_s']:.2f} s; "
        f"first batch {r['first_batch_s']:.2f} s; "
        f"{r['clips_per_s']:.1f} clips/s, {r['frames_per_s']:.0f} frames/s (after the first batch: "
        f"{r['steady_clips_per_s']:.1f} clips/s, {r['steady_frames_per_s']:.0f} frames/s)"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[2])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--mode", choices=MODES, default="person")
    ap.add_argument("--clip-len", type=int, default=16)
    ap.add_argument("--stride", type=int, default=8)
    ap.add_argument("--crop", type=int, default=224)
    ap.add_argument("--batch-size", type=int, default=8)
    ap.add_argument("--workers", type=int, default=min(8, os.cpu_count() or 1))
    ap.add_argument("--clips", type=int, default=512, help="clips per pass (a seeded random subset)")
    ap.add_argument("--passes", type=int, default=2, help="passes with fresh workers: the first is cold")
    ap.add_argument("--flip-prob", type=float, default=0.5)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)

    t0 = time.perf_counter()
    ds = SequenceDataset(
        args.dataset, clip_len=args.clip_len, stride=args.stride, mode=args.mode, crop=args.crop,
        flip_prob=args.flip_prob, seed=0,
    )  # fmt: skip
    build = time.perf_counter() - t0
    print(f"{args.dataset}: {len(ds)} clips of {args.clip_len} frames ({args.mode} mode, crop {args.crop}); "
          f"dataset built in {build:.2f} s")  # fmt: skip
    if not len(ds):
        print("no clips: nothing to measure", file=sys.stderr)
        return 1
    pick = np.random.default_rng(0).permutation(len(ds))[: args.clips].tolist()
    sub = Subset(ds, pick)
    print(f"{len(pick)} clips a pass, batch {args.batch_size}, {args.workers} workers, "
          f"{os.cpu_count()} cores, torch {torch.__version__}")  # fmt: skip
    for p in range(args.passes):
        print(
            report("cold" if p == 0 else f"warm {p}", measure(sub, args.batch_size, args.workers)), flush=True
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
