"""The MoveNet rows on the full training sets beside the same rows on the subsets, as a markdown table
(docs/transfer.md, "The rows on the full training sets").

    python experiments/transfer/movenet_table.py [--doc docs/transfer.md]

Reads ``docs/figures/transfer_movenet.json`` (the subsets of ``make movenet-data``) and
``docs/figures/transfer_movenet_full.json`` (``movenet_rows.py --data full``); prints one line a row
scored on the full sets, each cell ``subsets -> full``. With ``--doc`` the table replaces what stands
between ``<!-- movenet-full-table -->`` and ``<!-- /movenet-full-table -->`` in that file.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(Path(__file__).resolve().parent))
SUBSETS = ROOT / "docs/figures/transfer_movenet.json"
FULL = ROOT / "docs/figures/transfer_movenet_full.json"
MARK = ("<!-- movenet-full-table -->", "<!-- /movenet-full-table -->")
HEAD = (
    "| row | PA-MPJPE test (mm) | real PCK@0.1 (floor 56.7 %) | synthetic PCK@0.1 (floor 58.6 %) | "
    "transfer ratio @0.1 | its 90 % interval, full sets | real size (w, h), full sets | "
    "8 sub-pixel shifts, full sets: real PCK@0.1 mean (sd) / ratio | "
    "real PCK@0.1 under its MoveNet's own keypoints (the ceiling), full sets |\n"
    "|---|---:|---:|---:|---:|---:|---:|---:|---:|"
)
CEILING = {"movenet_lightning": "ceiling_lightning", "movenet_thunder": "ceiling_thunder"}
"""The ceiling row of each MoveNet (movenet_rows.ROWS): its own 2D keypoints, scored on the subsets' JSON."""


def _cells(e: dict | None) -> dict[str, float | None]:
    if e is None:
        return {"pa": None, "real": None, "syn": None, "ratio": None}
    t = e["transfer"]
    return {
        "pa": e.get("test", {}).get("pa_mpjpe_mm"),
        "real": 100 * t["real_pck@0.1"]["ours"],
        "syn": 100 * t["synthetic_pck@0.1"]["ours"],
        "ratio": t["ratio@0.1"],
    }


def _pair(a: float | None, b: float | None, fmt: str) -> str:
    def f(v: float | None) -> str:
        return "-" if v is None else format(v, fmt)

    return f"{f(a)} -> **{f(b)}**"


def _order(name: str) -> tuple[int, str]:
    """The order of movenet_rows.ROWS, each row's test-time-fit entries after it."""
    from movenet_rows import ROWS

    base = name.split("_fit")[0]
    return (list(ROWS).index(base) if base in ROWS else len(ROWS), name)


def _backbone(name: str) -> str:
    """The MoveNet of a row: its config's ``model.backbone`` (a WiSE-FT row: its first row's)."""
    import yaml
    from movenet_rows import ROWS

    base = name.split("_fit")[0]
    src = ROWS[base][1] if base in ROWS else "config"
    if src.startswith("wise:"):
        base = src.split(":")[1]
    cfg = ROOT / "configs/recovery/movenet" / f"{base}.yaml"
    return yaml.safe_load(cfg.read_text())["model"]["backbone"]


def _gap(subsets: dict, name: str, real: float) -> str:
    """Points of real PCK@0.1 under the row's MoveNet's ceiling row, and that ceiling."""
    c = subsets.get(CEILING.get(_backbone(name), ""))
    if c is None:
        return "no ceiling row"
    top = 100 * c["transfer"]["real_pck@0.1"]["ours"]
    return f"{top - real:.1f} (of {top:.1f} %)"


def table(subsets: dict, full: dict) -> str:
    lines = [HEAD]
    for name in sorted(full, key=_order):
        e = full[name]
        s, f = _cells(subsets.get(name)), _cells(e)
        t = e["transfer"]
        lo, hi = t["ratio_90"]
        w, h = t["extent_ratio_real"]
        j = e.get("jitter")
        jit = (f"{100 * j['real_pck_mean']:.1f} % ({100 * j['real_pck_sd']:.1f}) / {j['ratio_mean']:.2f}"
               if j else "not run")
        lines.append(
            f"| `{name}` | {_pair(s['pa'], f['pa'], '.1f')} | {_pair(s['real'], f['real'], '.1f')} | "
            f"{_pair(s['syn'], f['syn'], '.1f')} | {_pair(s['ratio'], f['ratio'], '.2f')} | "
            f"{lo:.2f} to {hi:.2f} | {w:.2f}, {h:.2f} | {jit} | {_gap(subsets, name, f['real'])} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--doc", type=Path, help="replace the table between the markers in this file")
    args = ap.parse_args(argv)
    for p in (SUBSETS, FULL):
        if not p.is_file():
            print(f"{p}: missing; run experiments/transfer/movenet_rows.py first", file=sys.stderr)
            return 2
    text = table(json.loads(SUBSETS.read_text()), json.loads(FULL.read_text()))
    if args.doc is None:
        print(text)
        return 0
    doc = args.doc.read_text()
    a, b = doc.find(MARK[0]), doc.find(MARK[1])
    if a < 0 or b < a:
        print(f"{args.doc}: no {MARK[0]} ... {MARK[1]} markers", file=sys.stderr)
        return 2
    args.doc.write_text(doc[: a + len(MARK[0])] + "\n" + text + "\n" + doc[b:])
    return 0


if __name__ == "__main__":
    sys.exit(main())
