"""Training images/s of HMR-BLSM on MoveNet against the packaged EfficientNet-Lite0 recipe, side by side;
written to the ``recovery_movenet`` section of ``docs/benchmarks.md``.

Each condition is a full ``recovery.tasks.hmr_task.HMRTask`` training step (network, BLSM, losses,
discriminator, AdamW) on the same dataset's batches from the real loader (the crop cache at the
condition's crop size, BatchAugment), held in memory so that only the step is timed. Conditions
alternate in rounds so that machine load affects them alike; the table gives medians and each
condition's speed over Lite0's.

    python benchmarks/bench_movenet_train.py --dataset out/data/val --out docs/benchmarks.md
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).parent))

from report import write_section  # noqa: E402

from recovery.config import DataConfig, ModelConfig, RecoveryConfig, TrainConfig  # noqa: E402
from recovery.datasets.loaders import loaders  # noqa: E402
from recovery.train import setup  # noqa: E402

CONDITIONS = {  # name -> (model settings, crop)
    "Lite0, ImageNet, all trained, 128 px (the packaged recipe)": ({"backbone": "efficientnet_lite0"}, 128),
    "MoveNet Lightning fixed, pooled trunk, 192 px": (
        {"backbone": "movenet_lightning", "train_blocks": 0},
        192,
    ),
    "MoveNet Lightning fixed, keypoints, 192 px": (
        {"backbone": "movenet_lightning", "train_blocks": 0, "head_input": "keypoints"},
        192,
    ),
    "MoveNet Lightning fixed, keypoints + pooled, 192 px": (
        {
            "backbone": "movenet_lightning",
            "train_blocks": 0,
            "head_input": "keypoints+pooled",
            "image_dropout": 0.5,
        },
        192,
    ),
    "MoveNet Lightning, last 4 blocks trained, keypoints + pooled, 192 px": (
        {
            "backbone": "movenet_lightning",
            "train_blocks": 4,
            "head_input": "keypoints+pooled",
            "image_dropout": 0.5,
        },
        192,
    ),
    "MoveNet Lightning all trained, keypoints + pooled, 192 px": (
        {"backbone": "movenet_lightning", "head_input": "keypoints+pooled", "image_dropout": 0.5},
        192,
    ),
    "MoveNet Lightning fixed, keypoints, 128 px": (
        {"backbone": "movenet_lightning", "train_blocks": 0, "head_input": "keypoints"},
        128,
    ),
    "MoveNet Thunder fixed, keypoints, 256 px": (
        {"backbone": "movenet_thunder", "train_blocks": 0, "head_input": "keypoints"},
        256,
    ),
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument(
        "--dataset", default="out/data/val", help="a synth dataset (its caches are built if missing)"
    )
    ap.add_argument("--out", default="docs/benchmarks.md")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--steps", type=int, default=4, help="timed steps per round and condition")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args(argv)
    if not (Path(args.dataset) / "manifest.json").is_file():
        print(
            f"bench_movenet_train: error: {args.dataset}: no dataset (make recovery-data, or --dataset DIR)",
            file=sys.stderr,
        )
        return 2
    torch.set_num_threads(2)
    tasks = {}
    for name, (model, crop) in CONDITIONS.items():
        cfg = RecoveryConfig(
            model=ModelConfig(**model),
            data=DataConfig(train=(args.dataset,), val="", crop=crop, workers=0),
            train=TrainConfig(steps=10**6, batch_size=args.batch, threads=2),
        )
        task, train, _ = setup(cfg, log=lambda *_: None)
        make_loader, _ = loaders(cfg, task, train, None)
        task.to(torch.device("cpu"))
        it = make_loader(0)
        batches = [next(it) for _ in range(args.steps)]
        task.training_step(batches[0], 0)  # warm-up
        tasks[name] = (task, batches)
    speeds: dict[str, list[float]] = {n: [] for n in tasks}
    for r in range(args.rounds):
        for name, (task, batches) in tasks.items():
            t0 = time.perf_counter()
            for b in batches:
                task.training_step(b, 0)
            speeds[name].append(args.steps * args.batch / (time.perf_counter() - t0))
        print(
            f"[bench] round {r + 1}: "
            + "; ".join(f"{n.split(',')[0]}.. {v[-1]:.1f}" for n, v in speeds.items())
        )
    med = {n: sorted(v)[len(v) // 2] for n, v in speeds.items()}
    base = med[next(iter(CONDITIONS))]
    lines = [
        f"Measured {time.strftime('%Y-%m-%d')} on {platform.machine()}, {torch.get_num_threads()} torch threads, "
        f"torch {torch.__version__}: one HMR-BLSM training step (network, BLSM, losses, the 47-D discriminator, AdamW), "
        f"batch {args.batch}, batches of `{args.dataset}` from the real loader held in memory. "
        f"Median of {args.rounds} alternating rounds of {args.steps} steps.",
        "",
        "| condition | training images / s | over Lite0 |",
        "| --- | ---: | ---: |",
        *[f"| {n} | {v:.1f} | {v / base:.2f}x |" for n, v in med.items()],
        "",
        "Rounds: " + "; ".join(f"{n}: {', '.join(f'{x:.1f}' for x in v)}" for n, v in speeds.items()) + ".",
    ]
    write_section(
        Path(args.out),
        "recovery_movenet",
        "HMR-BLSM on MoveNet: training images/s against Lite0 (CPU)",
        "benchmarks/bench_movenet_train.py",
        lines,
    )
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
