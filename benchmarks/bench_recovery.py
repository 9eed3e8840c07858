"""HMR-BLSM throughput: training images/s with the real loader against in-memory batches, and
inference images/s; written to the ``recovery`` section of ``docs/benchmarks.md``.

The real loader is what ``recovery train`` uses: the pre-cropped cache (memory-mapped uint8 crops),
:class:`recovery.datasets.augment.BatchAugment` (affine warp of image, mask and parts, colour jitter, label
transforms) in ``workers`` DataLoader processes. The in-memory condition feeds the same number of
steps from batches augmented beforehand and held in memory, so only the network's step is timed.
The two conditions alternate in rounds so that machine load affects both alike; the ratio is real
loader / in-memory images per second (target >= 0.9). A third condition times the same in-memory
batches with the backbone's weights and images in the default contiguous (NCHW) memory format
(``train.channels_last: false``) against channels-last, the trainer's default.

    python benchmarks/bench_recovery.py --dataset out/data/val --out docs/benchmarks.md
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--dataset", default="out/data/val", help="a synth dataset (its cache is built if missing)")
    ap.add_argument("--out", default="docs/benchmarks.md")
    ap.add_argument("--backbone", default="efficientnet_lite0")
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--steps", type=int, default=12, help="timed steps per round and condition")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--workers", type=int, default=0, help="loader workers (0: augment in the main process, best on 2 cores)")
    args = ap.parse_args(argv)
    if not (Path(args.dataset) / "manifest.json").is_file():
        print(f"bench_recovery: error: {args.dataset}: no dataset (make recovery-data, or --dataset DIR)", file=sys.stderr)
        return 2
    torch.set_num_threads(2)
    cfg = RecoveryConfig(
        model=ModelConfig(backbone=args.backbone, pretrained=args.backbone.startswith("efficientnet")),
        data=DataConfig(train=(args.dataset,), val="", crop=args.crop, workers=args.workers),
        train=TrainConfig(steps=10**6, batch_size=args.batch),
    )
    task, train, _ = setup(cfg, log=lambda *_: None)
    make_loader, _ = loaders(cfg, task, train, None)
    task.to(torch.device("cpu"))
    it = make_loader(0)
    memory = [next(it) for _ in range(args.steps)]
    for b in memory[:3]:  # warm-up
        task.training_step(b, 0)

    def timed(source) -> float:
        t0 = time.perf_counter()
        for _ in range(args.steps):
            task.training_step(next(source), 0)
        return args.steps * args.batch / (time.perf_counter() - t0)

    backbone = task.model.backbone
    real, mem, nchw = [], [], []
    for r in range(args.rounds):
        loader = make_loader(args.steps * (r + 1) * args.batch)
        next(loader)  # workers started and the queue filled, as in a run's steady state
        real.append(timed(loader))
        mem.append(timed(iter(memory * 2)))
        backbone.use_channels_last(False)  # train.channels_last: false, same batches
        task.training_step(memory[0], 0)
        nchw.append(timed(iter(memory * 2)))
        backbone.use_channels_last(True)
        print(f"[bench] round {r + 1}: real loader {real[-1]:.1f} img/s, in memory {mem[-1]:.1f} img/s, "
              f"in memory with contiguous (NCHW) weights {nchw[-1]:.1f} img/s")
    med = lambda xs: sorted(xs)[len(xs) // 2]  # noqa: E731
    real_ips, mem_ips, nchw_ips = med(real), med(mem), med(nchw)

    model, body = task.model.eval(), task.body
    images = torch.rand(args.batch, 3, args.crop, args.crop)
    k = torch.tensor([[200.0, 0, args.crop / 2], [0, 200.0, args.crop / 2], [0, 0, 1]]).expand(args.batch, 3, 3)
    from recovery.models.hmr import predict_body

    with torch.no_grad():
        predict_body(body, model(images), k, args.crop)
        t0 = time.perf_counter()
        n = 0
        while time.perf_counter() - t0 < 10:
            predict_body(body, model(images), k, args.crop)
            n += args.batch
        infer = n / (time.perf_counter() - t0)
    lines = [
        f"Measured {time.strftime('%Y-%m-%d')} on {platform.machine()}, {torch.get_num_threads()} torch threads, "
        f"torch {torch.__version__}: {args.backbone} at {args.crop} px, batch {args.batch}, 3 IEF iterations, "
        f"the 47-D discriminator, AdamW; {args.workers} loader worker(s) on `{args.dataset}`'s cache. "
        f"Median of {args.rounds} alternating rounds of {args.steps} steps.",
        "",
        "| | images / s | ratio |",
        "| --- | ---: | ---: |",
        f"| training, in-memory batches | {mem_ips:.1f} | |",
        f"| training, in-memory batches, `train.channels_last: false` | {nchw_ips:.1f} | "
        f"channels-last **{mem_ips / nchw_ips:.2f}x** |",
        f"| training, real loader (cache + BatchAugment, {args.workers} worker) | {real_ips:.1f} | **{real_ips / mem_ips:.2f}** (target >= 0.9) |",
        f"| inference (network + BLSM, no grad) | {infer:.1f} | |",
        "",
        f"Rounds: real {', '.join(f'{x:.1f}' for x in real)}; in memory {', '.join(f'{x:.1f}' for x in mem)}; "
        f"in memory, contiguous weights {', '.join(f'{x:.1f}' for x in nchw)}.",
    ]
    write_section(Path(args.out), "recovery", "HMR-BLSM training and inference throughput (CPU)",
                  "benchmarks/bench_recovery.py", lines)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
