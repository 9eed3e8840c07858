"""Train the packaged landmark detector (blsm/data/landmark_detector.pt) on training stand-in scans.

    python scripts/landmark_detector.py --out out/lmdet            # populations, renders, training
    python experiments/registration/register4d.py scans out/register4d/heldout/scans/*.npz --keypoints detector

Training populations (textured, default scanner artefacts; seeds 4301-4304, none of them in any
measurement): 60 subjects rest + posed (pose prior), 16 with a stool and 8 floor markers, 8 without
feet, 80 more rest + posed: 328 scans, 18 views each, plus 40 scenes without a person. See
docs/markerless.md ("A learnt landmark detector").
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import torch

POPULATIONS = {  # name: (subjects, seed, Artefacts keywords)
    "plain": (60, 4301, {}),
    "props": (16, 4302, {"stool": True, "floor_markers": 8}),
    "nofeet": (8, 4303, {"missing_feet": True}),
    "plain2": (80, 4304, {}),
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=Path("out/lmdet"))
    ap.add_argument("--epochs", type=int, default=12)
    ap.add_argument("--size", type=int, default=192)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--init", default=None, help="start from this detector file")
    ap.add_argument("--tag", default="", help="suffix of the output file name")
    ap.add_argument(
        "--package", action="store_true", help="copy the result to blsm/data/landmark_detector.pt"
    )
    args = ap.parse_args()
    from blsm.learn.markerless.landmark_detector import (
        DetectorTrainConfig,
        make_negative_views,
        make_training_views,
        train_detector,
    )
    from blsm.learn.scans.format import landmark_names
    from blsm.learn.scans.population import Artefacts, make_population

    log = lambda m: print(m, file=sys.stderr, flush=True)  # noqa: E731
    for name, (n, seed, art) in POPULATIONS.items():
        if not (args.out / name / "index.json").exists():
            make_population(
                args.out / name, n, n, 1, seed=seed, test_fraction=0.0, artefacts=Artefacts(**art)
            )
    views = make_training_views([args.out / n for n in POPULATIONS], args.out / "views.npz", 0, log)
    neg = make_negative_views(40, args.out / "views.negatives.npz", len(landmark_names()), 0)
    torch.set_num_threads(2)
    target = args.out / f"landmark_detector_{args.size}{args.tag}.pt"
    cfg = DetectorTrainConfig(size=args.size, epochs=args.epochs, lr=args.lr, init=args.init)
    train_detector([views, neg], target, cfg, log)
    if args.package:
        from blsm.pose2d.landmark_net import DEFAULT_WEIGHTS

        shutil.copyfile(target, DEFAULT_WEIGHTS)
        log(f"packaged {target} -> {DEFAULT_WEIGHTS}")


if __name__ == "__main__":
    main()
