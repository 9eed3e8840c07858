"""``blsm leap train CONFIG --out DIR [--resume]`` and ``blsm leap evaluate DIR``
(:mod:`blsm.leap.train`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


def load_config(path: str | Path) -> Any:
    from blsm.config import config_from_dict
    from blsm.io import read_yaml
    from blsm.leap.train import LeapTrainConfig

    return config_from_dict(LeapTrainConfig, read_yaml(path, "LEAP training config"), str(path))


def cmd_train(args: argparse.Namespace) -> int:
    from blsm.leap.train import train

    cfg = load_config(args.config)
    if args.occupancy_steps is not None:
        import dataclasses

        cfg = dataclasses.replace(cfg, occupancy_steps=args.occupancy_steps)
    print(f"[leap] checkpoint {train(cfg, Path(args.out), resume=args.resume)}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    import numpy as np

    import blsm
    from blsm.leap.train import evaluate, load_run

    run = Path(args.run)
    ck_path = run / "last.pt"
    if not ck_path.is_file() or not (run / "data.npz").is_file():
        raise ValueError(f"{run}: no LEAP run here (last.pt and data.npz)")
    model = blsm.load()
    leap, cfg, ck = load_run(ck_path, model)  # evaluated here, on the CPU
    with np.load(run / "data.npz") as d:
        data = {k: d[k] for k in d.files}
    res = {"step": ck["step"], "cycle": cfg.net.cycle, "held_out_clips": [str(c) for c in data["held_out_clips"]]}
    for split in ("unseen_poses", "unseen_subjects"):
        res[split] = evaluate(leap, data, split)
        if args.chamfer:
            from blsm.leap.mesh import chamfer, grid_box, reconstruct, true_meshes

            n = min(args.chamfer, len(data[f"{split}_B"]))
            verts = true_meshes(model, data[f"{split}_B"][:n], data[f"{split}_subject"][:n])
            faces, rng = model.faces.numpy(), np.random.default_rng(0)
            cd = [chamfer(reconstruct(leap, data[f"{split}_B"][i], *grid_box(verts[i]), args.res), (verts[i], faces),
                          10000, rng) for i in range(n)]  # fmt: skip
            res[split].update({"chamfer_mm": round(1000.0 * float(np.mean(cd)), 2), "chamfer_bodies": n, "grid": args.res})
    text = json.dumps(res, indent=1)
    print(text)
    (run / "metrics.json").write_text(text + "\n")
    return 0


def add_parser(sub: Any) -> None:
    p = sub.add_parser("leap", help="LEAP occupancy networks on BLSM's bones: train, evaluate")
    lsub = p.add_subparsers(dest="leap_cmd", required=True)
    t = lsub.add_parser("train", help="train both stages (resumable)")
    t.add_argument("config", help="configs/leap/*.yaml")
    t.add_argument("--out", required=True)
    t.add_argument("--resume", action="store_true")
    t.add_argument("--occupancy-steps", type=int, help="stage 2's steps instead of the config's (with --resume: extends a run)")
    t.set_defaults(func=cmd_train)
    e = lsub.add_parser("evaluate", help="IoU on unseen poses and unseen subjects into RUN/metrics.json")
    e.add_argument("run")
    e.add_argument("--chamfer", type=int, default=0, metavar="N",
                   help="also the Chamfer distance of the marching-cubes surface on each test set's first N bodies")
    e.add_argument("--res", type=int, default=64, help="the grid's nodes per axis for --chamfer (default 64)")
    e.set_defaults(func=cmd_evaluate)
