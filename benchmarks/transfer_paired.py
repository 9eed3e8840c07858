"""Paired differences between the rows of the transfer ablation (docs/transfer.md): for each row,
its gain over the floor minus the reference row's, on the same people, with a 90 % bootstrap
interval over people (photographs and synthetic images apart), and its transfer ratio's change.

    python benchmarks/transfer_paired.py [--reference base] [--rows ...]
        [--json docs/figures/transfer_paired.json]

Reads the checkpoints of out/transfer/runs/ROW/last.pt (``packaged``: the packaged one) and the
reference answers cached by ``recovery transfer`` in out/transfer/check/base/reference.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.transfer_ablation import ROWS  # noqa: E402
from recovery.eval import transfer as T  # noqa: E402
from recovery.predictor import load_predictor  # noqa: E402


def checkpoint(row: str) -> str:
    return "default" if row == "packaged" else str(ROOT / "out/transfer/runs" / row / "last.pt")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference", default="base")
    ap.add_argument("--rows", nargs="+", help="rows of benchmarks/transfer_ablation.py (default: all but --reference)")
    ap.add_argument("--json", default=str(ROOT / "docs/figures/transfer_paired.json"))
    ap.add_argument("--boot", type=int, default=2000)
    args = ap.parse_args()
    args.rows = args.rows or [r for r in ROWS if r != args.reference]
    torch.set_num_threads(2)
    cache = ROOT / "out/transfer/check/base/reference.json"
    command = T.reference_command(None)
    domains = {"real": T.read_boxes(ROOT / "out/transfer_dev"),
               "synthetic": T.synthetic_people(ROOT / "out/data/test", ROOT / "out/transfer/check/base/synthetic_images", 400)}
    hits: dict[str, dict[str, np.ndarray]] = {}
    setup = {}
    for name, people in domains.items():
        ref = T.run_reference(people, command, cache)
        vis = T.visible_joints(ref, [p.size for p in people])
        centre, side, ok = T.person_boxes(ref, vis)
        floor = T.mean_pose_floor(ref, vis, centre, side, ok)
        setup[name] = (people, ref, vis, centre, side, ok)
        hits[name] = {"joints": vis[ok].sum(1), "floor": T.hits(floor[ok], ref[ok], vis[ok], side[ok], 0.1)}
    for row in [args.reference, *args.rows]:
        pr = load_predictor(checkpoint(row))
        for name, (people, ref, vis, centre, side, ok) in setup.items():
            ours, _ = T.predict_joints(pr, people, centre, side, ok)
            hits[name][row] = T.hits(ours[ok], ref[ok], vis[ok], side[ok], 0.1)
    rng = np.random.default_rng(0)
    out = []
    for row in args.rows:
        res = {"row": row, "reference": args.reference}
        draws = {}
        for name, h in hits.items():
            n = len(h["joints"])
            idx = np.concatenate([np.arange(n)[None], rng.integers(0, n, (args.boot, n))])
            j = h["joints"][idx].sum(1)
            d = (h[row][idx].sum(1) - h[args.reference][idx].sum(1)) / j  # the gain's change (the floor cancels)
            gain_row = (h[row][idx].sum(1) - h["floor"][idx].sum(1)) / j
            gain_ref = (h[args.reference][idx].sum(1) - h["floor"][idx].sum(1)) / j
            draws[name] = (gain_row, gain_ref)
            res[name] = {"gain_change": float(d[0]), "interval_90": [float(np.percentile(d[1:], 5)), float(np.percentile(d[1:], 95))]}
        ratio = draws["real"][0] / draws["synthetic"][0] - draws["real"][1] / draws["synthetic"][1]
        res["ratio_change"] = float(ratio[0])
        res["ratio_change_90"] = [float(np.percentile(ratio[1:], 5)), float(np.percentile(ratio[1:], 95))]
        out.append(res)
        print(f"{row} vs {args.reference}: real gain {100 * res['real']['gain_change']:+.1f} points "
              f"({100 * res['real']['interval_90'][0]:+.1f} to {100 * res['real']['interval_90'][1]:+.1f}), synthetic "
              f"{100 * res['synthetic']['gain_change']:+.1f} ({100 * res['synthetic']['interval_90'][0]:+.1f} to "
              f"{100 * res['synthetic']['interval_90'][1]:+.1f}); ratio {res['ratio_change']:+.2f} "
              f"({res['ratio_change_90'][0]:+.2f} to {res['ratio_change_90'][1]:+.2f})", flush=True)
    Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
