"""What more budget would give to the best lever combination (docs/transfer.md, "More budget for the
best combination").

The row ``garments_effects_subjects`` (garments on 240 Anny people with the camera, sensor and
occlusion effects) moved the transfer ratio most at the ablation's budget of 800 steps of 32 on
1600 samples. These runs repeat its recipe with more training steps (800, 1600, 3200) and more data
(the seed's first 1600 or 3200 samples of configs/synth/transfer/garments_subjects.yaml), on a lent
GPU from carried crops (:mod:`experiments.transfer.gpu_carry`), configs
``configs/recovery/transfer/budget/d{samples}_s{steps}.yaml``:

    synth generate configs/synth/transfer/garments_subjects.yaml --out out/transfer/data/garments_subjects_3200 --num 3200 --part 2/2 --workers 2 --resume
    synth generate configs/synth/transfer/garments_subjects.yaml --out out/transfer/data/garments_subjects_3200 --num 3200 --part 1/2 --workers 2 --resume
    synth merge out/transfer/data/garments_subjects_3200
    python experiments/transfer/transfer_budget.py carry            # here: out/gpucarry_budget
    # there (device run, carry out/gpucarry_budget):
    python3 experiments/transfer/transfer_budget.py run --limit 500 --out $OUT   (483 s on an H200)
    # back here: the exported RUN.pt files into out/transfer/budget/runs/, then
    python experiments/transfer/transfer_budget.py score            # docs/figures/transfer_budget.json

``score`` scores each exported network as an ablation row is scored
(:func:`experiments.transfer.transfer_ablation.score`: PA-MPJPE on the held-out test set, the transfer check on
the development set) and, with ``--wise``, its half-and-half weight average with the 9000-step
network (as the packaged checkpoint was made).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from experiments.transfer.gpu_carry import add_commands, command  # noqa: E402

CARRY = ROOT / "out" / "gpucarry_budget"
RUNS = {"d1600_s800": (1600, 800), "d1600_s3200": (1600, 3200), "d3200_s800": (3200, 800),
        "d3200_s1600": (3200, 1600), "d3200_s3200": (3200, 3200)}
OUT = ROOT / "out" / "transfer" / "budget"
FIGURE = ROOT / "docs" / "figures" / "transfer_budget.json"


def configs(names: list[str]) -> dict[str, str]:
    return {n: f"configs/recovery/transfer/budget/{n}.yaml" for n in names}


def steps_reached(name: str) -> int | None:
    """The last step a run logged (``OUT/logs/NAME.log.jsonl``), None without a log."""
    log = OUT / "logs" / f"{name}.log.jsonl"
    if not log.is_file():
        return None
    steps = [json.loads(line).get("step") for line in log.read_text().splitlines() if line.strip()]
    return max((s for s in steps if isinstance(s, int)), default=None)


def score_runs(names: list[str], wise: bool) -> dict:
    from experiments.transfer.transfer_ablation import BASE_WEIGHTS, base_weights, headline, score, summary
    from recovery.checkpoint import average_checkpoints

    base_weights()
    rows = json.loads(FIGURE.read_text()) if FIGURE.is_file() else {}
    log = OUT / "budget.log"
    for name in names:
        samples, steps = RUNS[name]
        ck = OUT / "runs" / f"{name}.pt"
        if not ck.is_file():
            raise SystemExit(f"transfer_budget: {ck}: missing (train it on a GPU: module docstring)")
        todo, reached = [(name, ck)], steps_reached(name)
        if wise:
            avg = OUT / "runs" / f"wise_{name}.pt"
            average_checkpoints([(BASE_WEIGHTS, 0.5), (str(ck), 0.5)], avg)
            todo.append((f"wise_{name}", avg))
        for key, path in todo:
            m, rep = score(str(path), OUT / "eval" / key, OUT / "check" / key, log, {})
            rows[key] = {"samples": samples, "steps": steps, "steps_reached": reached, "crops": steps * 32,
                         "wise": key != name, "mpjpe_mm": m["mpjpe_mm"], **summary(m, rep)}
            print(f"[budget] {key}: {headline(rows[key])}", flush=True)
            FIGURE.write_text(json.dumps(rows, indent=1))
    return rows


def plot(rows: dict, out: Path) -> Path:
    """The curves: transfer ratio (90 % interval) and test PA-MPJPE against the fine-tuning crops,
    per amount of data, for the fine-tunes and their weight averages."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for samples, colour in ((1600, "tab:blue"), (3200, "tab:orange")):
        for wise, style in ((False, "o-"), (True, "s--")):
            pts = sorted((r["crops"], r) for r in rows.values() if r["samples"] == samples and r["wise"] == wise)
            if not pts:
                continue
            x = np.array([c for c, _ in pts]) / 1000
            label = f"{samples} samples" + (", averaged with the 9000-step network" if wise else "")
            ratio = np.array([r["transfer_ratio@0.1"] for _, r in pts])
            lo, hi = (np.array([r["transfer_ratio_90"][i] for _, r in pts]) for i in (0, 1))
            axes[0].errorbar(x * (1.02 if wise else 1.0), ratio, yerr=[ratio - lo, hi - ratio], fmt=style, color=colour,
                             capsize=3, label=label)
            axes[1].plot(x, [r["pa_mpjpe_mm"] for _, r in pts], style, color=colour, label=label)
    axes[0].axhline(0.5, color="k", lw=0.8, ls=":", label="target 0.5")
    axes[0].axhline(0.0, color="grey", lw=0.8, label="mean-pose floor")
    axes[0].set(xscale="log", xlabel="fine-tuning crops (thousands)", ylabel="transfer ratio @0.1 (90 % interval)")
    axes[1].set(xscale="log", xlabel="fine-tuning crops (thousands)", ylabel="PA-MPJPE, held-out test set (mm)")
    for ax in axes:
        ax.set_xticks([25.6, 51.2, 102.4], ["25.6", "51.2", "102.4"])
        ax.minorticks_off()
    axes[0].legend(fontsize=7)
    fig.suptitle("garments_effects_subjects: more steps and more data (GPU runs)")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c, r = add_commands(sub, limit=500.0)
    s = sub.add_parser("score")
    s.add_argument("--wise", action="store_true", help="also score each network averaged with the 9000-step one")
    sub.add_parser("plot", help="docs/figures/transfer_budget.png from docs/figures/transfer_budget.json")
    for p in (c, r, s):
        p.add_argument("--runs", nargs="+", default=list(RUNS), choices=list(RUNS))
    args = ap.parse_args(argv)
    if args.cmd in ("carry", "run"):
        return command(args, CARRY, configs(args.runs), "WEBP", 90)
    if args.cmd == "score":
        plot(score_runs(args.runs, args.wise), FIGURE.with_suffix(".png"))
    else:
        plot(json.loads(FIGURE.read_text()), FIGURE.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
