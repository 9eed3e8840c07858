"""The transfer ablation's backbone pair at the packaged network's crop budget, on a lent GPU
(docs/transfer.md, "The backbone pair at the packaged network's crop budget, on a GPU").

EfficientNet-Lite0 and Lite2 from ImageNet, each trained for 288k crops (the packaged network's
budget) on the `subjects` lever data (configs/synth/transfer/subjects.yaml: 240 Anny people,
2398 crops), with the configs ``configs/recovery/transfer/gpu_imagenet_lite{0,2}.yaml``, carried
and trained by :mod:`benchmarks.figures.gpu_carry` (the crops as JPEG quality 90):

    python benchmarks/figures/gpu_backbones.py carry      # here: out/gpucarry (32 MiB)
    # there (device run, carry out/gpucarry):
    python3 benchmarks/figures/gpu_backbones.py run --limit 440 --out $OUT
    # back here: each exported ROW.pt to out/transfer/runs/ROW/last.pt, then scored as the ablation rows are
    python benchmarks/transfer_ablation.py --rows gpu_imagenet_lite0 gpu_imagenet_lite2
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from benchmarks.figures.gpu_carry import make_carry, train  # noqa: E402

CARRY = ROOT / "out" / "gpucarry"
ROWS = ("gpu_imagenet_lite0", "gpu_imagenet_lite2")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("carry")
    c.add_argument("--wheels", default="/tmp/whl", help="folder holding kornia-0.9.0-py3-none-any.whl")
    r = sub.add_parser("run")
    r.add_argument("--limit", type=float, default=420.0, help="each training's wall-clock limit (s)")
    r.add_argument("--out", default=os.environ.get("OUT", "out/gpu_out"))
    args = ap.parse_args(argv)
    configs = {row: f"configs/recovery/transfer/{row}.yaml" for row in ROWS}
    if args.cmd == "carry":
        make_carry(CARRY, list(configs.values()), "JPEG", 90, Path(args.wheels))
        return 0
    outdir = Path(args.out)
    outdir.mkdir(parents=True, exist_ok=True)
    return train(CARRY, configs, args.limit, outdir)


if __name__ == "__main__":
    sys.exit(main())
