"""The training loader's cost of the style effects (docs/transfer.md, "Style"): one batch of 32
crops of a crop cache through :class:`recovery.datasets.augment.BatchAugment`, with no effect, with
RandConv, FDA, or both on every crop (probability 1, the most they cost), fresh items each round.

    python benchmarks/bench_style.py [--cache out/cache/base-...] [--rounds 5]
"""

from __future__ import annotations

import argparse
import glob
import statistics
import time

import torch

import blsm
from recovery.config import AugmentSpec, EffectsSpec
from recovery.datasets.augment import BatchAugment
from recovery.datasets.cache import CropCache

SETTINGS = {"none": EffectsSpec(), "randconv": EffectsSpec(randconv_prob=1.0),
            "fda": EffectsSpec(fda_prob=1.0, fda_folder="~/.cache/blsm-synth/backplates"),
            "both": EffectsSpec(randconv_prob=1.0, fda_prob=1.0, fda_folder="~/.cache/blsm-synth/backplates")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default=(sorted(glob.glob("out/cache/base-*")) or [""])[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--batch", type=int, default=32)
    args = ap.parse_args()
    torch.set_num_threads(2)
    cache = CropCache([args.cache])
    model = blsm.load()
    augs = {k: BatchAugment(128, cache.context, AugmentSpec(), 0, model.dof_mirror, cache.keypoint_names, effects=e)
            for k, e in SETTINGS.items()}
    times: dict[str, list[float]] = {k: [] for k in SETTINGS}
    for r in range(args.rounds):  # interleaved; every round new items (epoch r)
        items = [cache[(r, (r * args.batch + i) % len(cache))] for i in range(args.batch)]
        for k, aug in augs.items():
            t = time.perf_counter()
            aug(items)
            times[k].append(time.perf_counter() - t)
    base = statistics.median(times["none"])
    print(f"| effects | ms per batch of {args.batch} (median of {args.rounds}) | over none |")
    print("|---|---:|---:|")
    for k, v in times.items():
        m = statistics.median(v)
        print(f"| {k} | {1000 * m:.0f} | {m / base:.2f}x |")


if __name__ == "__main__":
    main()
