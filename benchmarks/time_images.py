"""Made the old-generator timings of docs/realism.md, "Measurements" (2026-11-26, fourth session; e92e556).

Seconds per image of whichever generator is on PYTHONPATH, timed as bench_realism.py's noise rows.

Subjects are made first (into WORK), then one warm-up image, then scenes 1-12, ROUNDS times; prints
JSON. Used to time an older checkout on the same config (docs/realism.md):

    git worktree add /tmp/old 7a686b6
    PYTHONPATH=/tmp/old python benchmarks/time_images.py \
        configs/synth/preview/noise_hdri.yaml out/time_old 3
"""

from __future__ import annotations

import argparse
import inspect
import json
import sys
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[2])
    ap.add_argument("config")
    ap.add_argument("work", help="folder for the subjects")
    ap.add_argument("rounds", type=int, nargs="?", default=3)
    args = ap.parse_args()
    torch.set_num_threads(1)

    sys.path.insert(0, str(Path(__file__).resolve().parent))  # benchmarks/, for bench_realism

    from bench_realism import time_scenes

    import blsm
    from blsm.mitsuba_util import resolve_variant
    from synth.config import load_config
    from synth.generate import prepare_subjects
    from synth.sample import SampleMaker

    cfg, work = load_config(args.config), Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    prepare_subjects(cfg, work, blsm.load())
    kw = {"threads": 0} if "threads" in inspect.signature(SampleMaker).parameters else {}  # older checkouts lack it
    maker = SampleMaker(cfg, work, resolve_variant(None), **kw)
    times = [time_scenes(maker, cfg.seed, 12)[1] for _ in range(args.rounds)]  # later rounds: warm-up again, cheap
    print(json.dumps({"s_per_image": times, "median": float(np.median(times))}))  # the median round, as bench_realism.py


if __name__ == "__main__":
    main()
