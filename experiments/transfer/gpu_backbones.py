"""The transfer ablation's backbone pair at the packaged network's crop budget, on a lent GPU
(docs/transfer.md, "The backbone pair at the packaged network's crop budget, on a GPU").

EfficientNet-Lite0 and Lite2 from ImageNet, each trained for 288k crops (the packaged network's
budget) on the `subjects` lever data (configs/synth/transfer/subjects.yaml: 240 Anny people,
2398 crops), with the configs ``configs/recovery/transfer/gpu_imagenet_lite{0,2}.yaml``, carried
and trained by :mod:`experiments.transfer.gpu_carry` (the crops as JPEG quality 90):

    python experiments/transfer/gpu_backbones.py carry      # here: out/gpucarry (32 MiB)
    # there (device run, carry out/gpucarry):
    python3 experiments/transfer/gpu_backbones.py run --limit 440 --out $OUT
    # back here: each exported ROW.pt to out/transfer/runs/ROW/last.pt, then scored as the ablation rows are
    python experiments/transfer/transfer_ablation.py --rows gpu_imagenet_lite0 gpu_imagenet_lite2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from experiments.transfer.gpu_carry import add_commands, command  # noqa: E402

CARRY = ROOT / "out" / "gpucarry"
ROWS = ("gpu_imagenet_lite0", "gpu_imagenet_lite2")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_commands(ap.add_subparsers(dest="cmd", required=True), limit=420.0)
    args = ap.parse_args(argv)
    return command(args, CARRY, {row: f"configs/recovery/transfer/{row}.yaml" for row in ROWS}, "JPEG", 90)


if __name__ == "__main__":
    sys.exit(main())
