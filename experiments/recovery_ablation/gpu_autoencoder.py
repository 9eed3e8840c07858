"""Made the runs in docs/figures/recovery_ablation_gpu.json (recovery_ablation.md "On a GPU"; db6cd71).

The mesh autoencoder at a GPU budget against PCA with as many components as its code
(docs/recovery_ablation.md, "On a GPU").

Trains ``--config`` (default ``configs/recovery/ablation_gpu/autoencoder.yaml``; CUDA when present) for at most
``--limit`` seconds (then it stops as on Ctrl-C, with a checkpoint, and the report says at which
step), and reports held-out vertex errors exactly as ``ablation.py`` beside it does for the CPU config
(:func:`experiments.recovery_ablation.ablation.autoencoder_report`). Needs ``out/motions_train`` and ``out/motions_test``.

    python experiments/recovery_ablation/gpu_autoencoder.py --out out/ablation_gpu
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from experiments.recovery_ablation.ablation import autoencoder_report, train_seconds  # noqa: E402
from recovery.checkpoint import read_checkpoint  # noqa: E402
from recovery.config import load_config  # noqa: E402
from recovery.train import train  # noqa: E402
from recovery.trainer import read_log  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default=str(ROOT / "configs/recovery/ablation_gpu/autoencoder.yaml"))
    ap.add_argument("--out", required=True, help="run folder; the report is OUT/autoencoder.json")
    ap.add_argument("--limit", type=float, default=420.0, help="training wall-clock limit (s)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    cfg = load_config(args.config)
    device = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"
    print(f"[gpu_autoencoder] device {device}; {cfg.train.steps} steps of {cfg.train.batch_size}; limit {args.limit:.0f} s")
    timer = threading.Timer(args.limit, lambda: os.kill(os.getpid(), signal.SIGINT))
    timer.start()
    t0 = time.perf_counter()
    try:
        status = train(cfg, out / "run", resume=True)
    finally:
        timer.cancel()
    wall = time.perf_counter() - t0
    rep = autoencoder_report(out / "run" / "last.pt", Path(args.config))
    recs = [r for r in read_log(out / "run" / "log.jsonl") if r["kind"] == "train"]
    rep.update(device=device, status=status, wall_s=wall, train_minutes=train_seconds(recs) / 60,
               planned_steps=cfg.train.steps, config=str(args.config),
               step=int(read_checkpoint(out / "run" / "last.pt")["step"]))
    (out / "autoencoder.json").write_text(json.dumps(rep, indent=1))
    print(json.dumps({k: rep[k] for k in ("device", "status", "step", "vertex_mm", "pca_vertex_mm",
                                          "train_vertex_mm", "train_pca_vertex_mm", "train_minutes")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
