"""Paired differences between the rows of the transfer ablation (docs/transfer.md): for each row,
its gain over the floor minus the reference row's, on the same people, with a 90 % bootstrap
interval over people (photographs and synthetic images apart), and its transfer ratio's change;
and, where both rows' evaluations kept ``people.npz``, the change of PA-MPJPE on the held-out test set,
person by person.

    python experiments/transfer/transfer_paired.py [--reference base] [--rows ...]
        [--json docs/figures/transfer_paired.json]

Reads the checkpoints of out/transfer/runs/ROW/last.pt (``packaged``: the 9000-step network; ``default``: the
packaged one; a run of experiments/transfer/transfer_budget.py: out/transfer/budget/runs/ROW.pt) and the
reference answers cached by ``recovery transfer`` in out/transfer/check/base/reference.json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from experiments.transfer.transfer_ablation import ROWS, checkpoint_of  # noqa: E402
from recovery.eval import transfer as T  # noqa: E402
from recovery.predictor import load_predictor  # noqa: E402


def locate(row: str) -> tuple[str, Path]:
    """A row's checkpoint and its ``recovery evaluate`` folder: an ablation row, or a run (or its
    weight average) of experiments/transfer/transfer_budget.py."""
    if row in ROWS:
        return checkpoint_of(row, ROOT / "out/transfer"), ROOT / "out/transfer/eval" / row
    ck = ROOT / "out/transfer/budget/runs" / f"{row}.pt"
    if not ck.is_file():
        raise SystemExit(f"transfer_paired: {row}: not an ablation row, and {ck} is missing")
    return str(ck), ROOT / "out/transfer/budget/eval" / row


def paired_pa_mpjpe(row: str, reference: str, boot: int, rng: np.random.Generator) -> dict | None:
    """The row's PA-MPJPE on the held-out test set minus the reference row's, person by person, with
    a 90 % bootstrap interval over people; None unless both rows' ``recovery evaluate`` kept
    ``people.npz`` (made since 2026-11-27)."""
    files = [locate(r)[1] / "people.npz" for r in (row, reference)]
    if not all(f.is_file() for f in files):
        return None
    (ia, a), (ib, b) = ((z["index"], z["pa_mpjpe_mm"]) for z in (np.load(f) for f in files))
    if not np.array_equal(ia, ib):
        raise SystemExit(f"{files[0]}: not the same test people as {files[1]}")
    d = a - b
    means = d[rng.integers(0, len(d), (boot, len(d)))].mean(1)
    return {"pa_mpjpe_change_mm": float(d.mean()),
            "interval_90": [float(np.percentile(means, 5)), float(np.percentile(means, 95))]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference", default="base")
    ap.add_argument("--rows", nargs="+", help="rows of experiments/transfer/transfer_ablation.py or runs of experiments/transfer/transfer_budget.py "
                    "(default: every ablation row but --reference)")
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
        ref, vis, centre, side, ok = T.reference_boxes(people, command, cache)
        floor = T.mean_pose_floor(ref, vis, centre, side, ok)
        setup[name] = (people, ref, vis, centre, side, ok)
        hits[name] = {"joints": vis[ok].sum(1), "floor": T.hits(floor[ok], ref[ok], vis[ok], side[ok], 0.1)}
    for row in [args.reference, *args.rows]:
        pr = load_predictor(locate(row)[0])
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
        pa = paired_pa_mpjpe(row, args.reference, args.boot, rng)
        if pa:
            res["test_pa_mpjpe"] = pa
        out.append(res)
        print(f"{row} vs {args.reference}: real gain {100 * res['real']['gain_change']:+.1f} points "
              f"({100 * res['real']['interval_90'][0]:+.1f} to {100 * res['real']['interval_90'][1]:+.1f}), synthetic "
              f"{100 * res['synthetic']['gain_change']:+.1f} ({100 * res['synthetic']['interval_90'][0]:+.1f} to "
              f"{100 * res['synthetic']['interval_90'][1]:+.1f}); ratio {res['ratio_change']:+.2f} "
              f"({res['ratio_change_90'][0]:+.2f} to {res['ratio_change_90'][1]:+.2f})"
              + (f"; test PA-MPJPE {pa['pa_mpjpe_change_mm']:+.2f} mm ({pa['interval_90'][0]:+.2f} to "
                 f"{pa['interval_90'][1]:+.2f})" if pa else ""), flush=True)
    Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
