"""Weight-space ensembles of the transfer ablation's fine-tuned networks (docs/transfer.md, "Weight
averaging"): WiSE-FT (Wortsman et al., CVPR 2022: a network's weights and its fine-tune's
interpolated) and a uniform model soup (Wortsman et al., ICML 2022: several fine-tunes of the same
start averaged), both known to make fine-tuned networks more robust to a shift of domain.

    python experiments/transfer/transfer_soup.py [--only NAME ...]   # after transfer_ablation.py --rows base randconv fda subjects garments_effects_subjects

``wise_garments_effects_subjects`` is the packaged checkpoint (make recovery-model exports it).

Every network averaged starts from the 9000-step network (``train.init`` of the rows), so they share one
architecture (:func:`recovery.checkpoint.average_checkpoints`). Each soup is scored like an ablation row:
``recovery evaluate`` on the held-out test set and ``recovery transfer`` on the development set.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from experiments.transfer.transfer_ablation import BASE_WEIGHTS as BASE  # noqa: E402
from experiments.transfer.transfer_ablation import base_weights, headline, score, summary  # noqa: E402
from recovery.checkpoint import average_checkpoints  # noqa: E402

RUNS = "out/transfer/runs"
SOUPS = {  # name: [(checkpoint, weight)]
    "wise_subjects": [(BASE, 0.5), (f"{RUNS}/subjects/last.pt", 0.5)],
    "soup4": [(f"{RUNS}/{r}/last.pt", 1.0) for r in ("base", "randconv", "fda", "subjects")],
    "wise_garments_effects_subjects": [(BASE, 0.5), (f"{RUNS}/garments_effects_subjects/last.pt", 0.5)],
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/transfer/soups")
    ap.add_argument("--only", nargs="+", choices=list(SOUPS), help="these soups (default: all)")
    ap.add_argument("--no-score", action="store_true", help="only write the averaged checkpoints")
    args = ap.parse_args()
    out = ROOT / args.out
    base_weights()
    figure = ROOT / "docs/figures/transfer_soups.json"
    rows = json.loads(figure.read_text()) if figure.is_file() else {}
    for name in args.only or SOUPS:
        parts = SOUPS[name]
        ck = out / f"{name}.pt"
        average_checkpoints(parts, ck)  # always again: a second, and never stale after a retrained part
        if args.no_score:
            print(f"[soup] {name}: {ck}", flush=True)
            continue
        rows[name] = {"parts": parts, **summary(*score(str(ck), out / "eval" / name, out / "check" / name,
                                                         out / "soups.log", {}))}
        print(f"[soup] {name}: {headline(rows[name])}", flush=True)
    figure.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
