"""How fast a plain network learns LEAP's nearest-vertex skinning weights (issue 55), the probe behind
the input and loss choices of ``blsm/leap`` (docs/leap.md, "Why the first run did not learn").

A four-layer ReLU perceptron (width 128), with no encoders, learns the weights of the nearest vertex
from 300 training bodies of a LEAP run's data and is scored (L1, Table D.2's measure) on 30
unseen-pose bodies every 250 steps; batch 8 bodies x 1024 points, Adam, one thread.

- ``--net forward``: canonical point -> weights (the forward LBS network's task);
- ``--net inverse``: posed point -> weights; ``--input bones`` feeds the point in every bone's frame
  (``B_k^-1 x``), ``raw`` the posed point alone (it cannot know the pose: a floor);
- ``--octaves N``: sin/cos features (``blsm.leap.model.encode``); ``--loss ce|l1``.

    python experiments/leap/probe_lbs.py out/leap/cpu --net forward --octaves 4 --loss ce --steps 1500
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from blsm.leap.model import encode


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a LEAP run folder (its data.npz)")
    ap.add_argument("--net", choices=("forward", "inverse"), required=True)
    ap.add_argument("--input", choices=("raw", "bones"), default="raw")
    ap.add_argument("--octaves", type=int, default=0)
    ap.add_argument("--loss", choices=("l1", "ce"), default="l1")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--lr", type=float, default=1e-3)
    args = ap.parse_args(argv)
    torch.manual_seed(0)
    torch.set_num_threads(1)
    xk, wk = ("xc", "wc") if args.net == "forward" else ("x", "w")
    with np.load(args.run / "data.npz") as d:
        tr = {k: d[f"train_{k}"][:300] for k in ("B", xk, wk)}
        te = {k: d[f"unseen_poses_{k}"][:30] for k in ("B", xk, wk)}
    k = tr[wk].shape[-1]

    def feats(B: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        if args.input == "bones":
            lin, t = B[:, None, :, :, :3], B[:, None, :, :, 3]
            x = torch.linalg.solve(lin, (x[:, :, None] - t)[..., None])[..., 0]  # (n, m, K, 3)
        return encode(x, args.octaves).flatten(2)

    fin = 3 * (1 + 2 * args.octaves) * (k if args.input == "bones" else 1)
    net = nn.Sequential(nn.Linear(fin, 128), nn.ReLU(), *[m for _ in range(3) for m in (nn.Linear(128, 128), nn.ReLU())],
                        nn.Linear(128, k))  # fmt: skip
    opt = torch.optim.Adam(net.parameters(), args.lr)
    rng = np.random.default_rng(0)
    t0 = time.time()
    for step in range(1, args.steps + 1):
        bi = rng.integers(len(tr["B"]), size=8)
        pi = np.stack([rng.choice(tr[xk].shape[1], 1024, replace=False) for _ in range(8)])
        B, x, w = torch.from_numpy(tr["B"][bi]), torch.from_numpy(tr[xk][bi[:, None], pi]), torch.from_numpy(tr[wk][bi[:, None], pi])
        logits = net(feats(B, x))
        if args.loss == "ce":
            loss = -(w * logits.log_softmax(-1)).sum(-1).mean()
        else:
            loss = (logits.softmax(-1) - w).abs().sum(-1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % 250 == 0:
            with torch.no_grad():
                pred = net(feats(torch.from_numpy(te["B"]), torch.from_numpy(te[xk]))).softmax(-1)
                l1 = float((pred - torch.from_numpy(te[wk])).abs().sum(-1).mean())
            print(f"{args.net} {args.input} octaves {args.octaves} {args.loss}: step {step} test L1 {l1:.4f} ({time.time() - t0:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
