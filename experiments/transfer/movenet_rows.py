"""HMR-BLSM on MoveNet, row by row (docs/transfer.md, "A backbone that reads people in photographs").

    python experiments/transfer/movenet_rows.py [--rows kp_frozen kpimg_frozen ...] [--draws 8]

Each trained row is ``configs/recovery/movenet/ROW.yaml`` (one budget and one data set for all; the data
of ``make movenet-data``), trained with ``recovery train ... --resume`` into ``out/movenet/runs/ROW``, then
its ``last.pt`` is scored:

- ``recovery evaluate`` on the held-out synthetic test set ``out/data/test`` (held-out subjects, CMU clips
  007_12 and 005_20, the sunset.exr background): PA-MPJPE;
- ``recovery transfer`` on the real development set against MediaPipe Pose, with the same synthetic test
  set: PCK@0.1 per domain against each domain's floor, the transfer ratio and its 90 % interval;
- ``experiments/transfer/transfer_jitter.py``: the same with every crop centre moved by less than a pixel,
  ``--draws`` times (the check's sub-pixel noise).

``--data full`` trains and scores the same rows at the same budget on the full training sets of
``make recovery-data`` (out/data/train_hdri, train_sky, train_mocap: 3 x 10k images, 120 subjects each)
with the same seated-postures data: each row's config with ``data.train`` (and a ``train.init`` of
this script's runs) replaced, written to ``out/movenet_full/configs/ROW.yaml``; runs, scores and logs
under ``out/movenet_full``, results in ``docs/figures/transfer_movenet_full.json`` (issue 52 asks
for the rows on the full sets).

Rows without a config score what exists: ``ceiling_lightning`` / ``ceiling_thunder`` (MoveNet's own 2D
keypoints; no mesh, no PA-MPJPE) and ``lite0`` (the packaged EfficientNet-Lite0 checkpoint of
2026-11-27, kept as ``out/weights/hmr_blsm_lite0_default.pt``). Every step is resumable. Results:
``docs/figures/transfer_movenet.json`` (rows not run now keep their entries).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

BIN = Path(sys.executable).parent
TEST = "out/data/test"
REAL = "out/transfer_dev"
OUT = ROOT / "out/movenet"
JSON = ROOT / "docs/figures/transfer_movenet.json"
DATA = {  # --data: (training sets, output folder, results)
    "subsets": (None, OUT, JSON),
    "full": (
        ["out/data/train_hdri", "out/data/train_sky", "out/data/train_mocap", "out/movenet/data/garments_postures"],
        ROOT / "out/movenet_full",
        ROOT / "docs/figures/transfer_movenet_full.json",
    ),
}
LITE0 = "out/weights/hmr_blsm_lite0_default.pt"
ROWS = {  # name: (what it is, checkpoint or config)
    "ceiling_lightning": ("MoveNet Lightning's own 2D keypoints (192 px): the ceiling", "movenet_lightning"),
    "ceiling_thunder": ("MoveNet Thunder's own 2D keypoints (256 px)", "movenet_thunder"),
    "lite0": (
        "the packaged checkpoint of 2026-11-27 to 2026-12-06: ImageNet Lite0, 128 px, all trained "
        "(garments_effects_subjects WiSE-FT)",
        LITE0,
    ),
    "pooled_frozen": (
        "Lightning fixed, the regressor on the pooled stride-32 trunk map (the prototype), 192 px",
        "config",
    ),
    "kp_frozen": (
        "Lightning fixed, the regressor on MoveNet's 2D keypoints and confidences (lifting), 192 px",
        "config",
    ),
    "kpimg_frozen": (
        "Lightning fixed, keypoints + pooled trunk (layer-normalised, half the images dropped), 192 px",
        "config",
    ),
    "kpparts_frozen": (
        "Lightning fixed, keypoints + a spatial head over the stride-4 map read out at each keypoint "
        "(half the images dropped), 192 px",
        "config",
    ),
    "kpimg_last4": (
        "kpimg_frozen's recipe with the last 4 trunk blocks, the pyramid and the heads trained at 0.1x "
        "the rate",
        "config",
    ),
    "kpimg_all": (
        "kpimg_frozen's recipe with the whole of MoveNet trained at 0.1x the rate",
        "config",
    ),
    "kp_frozen_long": (
        "kp_frozen trained for 800 more steps (1600 in all; train.init, the schedule restarted)",
        "config",
    ),
    "wise_last4": (
        "WiSE-FT: the weights of kpimg_frozen and kpimg_last4 averaged half and half (same start, same seed)",
        "wise:kpimg_frozen:kpimg_last4",
    ),
    "kp_frozen_128": ("kp_frozen at 128 px crops (MoveNet below its native 192)", "config"),
    "thunder_kp_frozen": ("kp_frozen on MoveNet Thunder at 256 px", "config"),
}


def row_config(name: str, train: list[str] | None, out: Path) -> str:
    """The config of a trained row: ``configs/recovery/movenet/NAME.yaml``, or with ``train`` its copy
    that trains on those sets (and starts a continuation from this output's run), written under ``out``."""
    src = f"configs/recovery/movenet/{name}.yaml"
    if train is None:
        return src
    import yaml

    cfg = yaml.safe_load((ROOT / src).read_text())
    cfg["data"]["train"] = list(train)
    init = cfg.get("train", {}).get("init", "")
    if init.startswith("out/movenet/runs/"):
        cfg["train"]["init"] = _from_root(out / "runs" / init.removeprefix("out/movenet/runs/"))
    dst = out / "configs" / f"{name}.yaml"
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_text(f"# {src} on the full training sets (experiments/transfer/movenet_rows.py --data full)\n"
                   + yaml.safe_dump(cfg, sort_keys=False))
    return _from_root(dst)


def _from_root(path: Path) -> str:
    """``path`` relative to the repository (as the configs name their files), else absolute."""
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def run(cmd: list[str], log: Path) -> None:
    print("+", " ".join(cmd), flush=True)
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as fh:
        r = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT)
    if r.returncode != 0:
        raise SystemExit(f"movenet_rows: {' '.join(cmd)} failed (exit {r.returncode}); see {log}")


def score(name: str, checkpoint: str, draws: int, fit: int | None = None) -> dict:
    """Evaluate (not for the ceiling), transfer check and jitter of one checkpoint (with the test-time fit of
    ``fit`` iterations where given)."""
    res: dict = {"checkpoint": checkpoint, "fit": fit or 0}
    extra = ["--fit", str(fit)] if fit is not None else []
    ceiling = checkpoint.startswith("movenet_")
    if not ceiling:
        ev = OUT / "eval" / name
        if not (ev / "metrics.json").is_file():
            run(
                [str(BIN / "recovery"), "evaluate", checkpoint, TEST, "--out", str(ev), *extra],
                OUT / "logs" / f"{name}.log",
            )
        m = json.loads((ev / "metrics.json").read_text())
        res["test"] = {k: m[k] for k in ("mpjpe_mm", "pa_mpjpe_mm", "pve_mm") if k in m}
    check = OUT / "check" / name
    if not (check / "report.json").is_file():
        ref = ROOT / "out/transfer/check_default/reference.json"
        check.mkdir(parents=True, exist_ok=True)
        if ref.is_file() and not (check / "reference.json").is_file():
            shutil.copy(ref, check / "reference.json")  # the same people: MediaPipe need not run again
        run(
            [
                str(BIN / "recovery"),
                "transfer",
                checkpoint,
                "--real",
                REAL,
                "--synthetic",
                TEST,
                "--out",
                str(check),
                *extra,
            ],
            OUT / "logs" / f"{name}.log",
        )
    rep = json.loads((check / "report.json").read_text())
    res["transfer"] = {
        "ratio@0.1": rep["transfer_ratio@0.1"],
        "ratio_90": rep["transfer_ratio_90"],
        "ratio@0.2": rep["transfer_ratio@0.2"],
        **{f"{d}_pck@0.1": rep["domains"][d]["pck@0.1"] for d in ("real", "synthetic")},
        "extent_ratio_real": rep["domains"]["real"]["extent_ratio"],
    }
    jit = check / "jitter.json"
    if draws and not jit.is_file():
        run(
            [
                sys.executable,
                str(ROOT / "experiments/transfer/transfer_jitter.py"),
                checkpoint,
                "--check",
                str(check),
                "--draws",
                str(draws),
                "--json",
                str(jit),
                *extra,
            ],
            OUT / "logs" / f"{name}.log",
        )
    if jit.is_file():
        j = json.loads(jit.read_text())
        import numpy as np

        r = np.asarray(j["transfer_ratio_shifted"])
        s = np.asarray(j["real"]["pck@0.1_shifted"])
        res["jitter"] = {
            "draws": len(r),
            "ratio_mean": float(r.mean()),
            "ratio_sd": float(r.std(ddof=1)),
            "real_pck_mean": float(s.mean()),
            "real_pck_sd": float(s.std(ddof=1)),
        }
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    ap.add_argument("--draws", type=int, default=8)
    ap.add_argument(
        "--fit", type=int, help="score with the test-time fit of N iterations (rows named ROW_fitN)"
    )
    ap.add_argument("--data", choices=list(DATA), default="subsets",
                    help="subsets: the data of make movenet-data; full: the training sets of make recovery-data")
    args = ap.parse_args(argv)
    global OUT, JSON
    train_sets, OUT, JSON = DATA[args.data]
    for name in args.rows:
        what, src = ROWS[name]
        if train_sets is not None and not (src == "config" or src.startswith("wise:")):
            print(f"[movenet] {name}: no training, the same on any data (its row of {DATA['subsets'][2].name})")
            continue
        t0 = time.time()
        if src == "config":
            cfg = row_config(name, train_sets, OUT)
            run_dir = OUT / "runs" / name
            if not (run_dir / ".trained").is_file():  # an interrupted run continues
                run(
                    [str(BIN / "recovery"), "train", cfg, "--out", str(run_dir), "--resume"],
                    OUT / "logs" / f"{name}.log",
                )
                (run_dir / ".trained").write_text(time.strftime("%Y-%m-%d %H:%M"))
            checkpoint = str(run_dir / "last.pt")
        elif src.startswith("wise:"):
            from recovery.checkpoint import average_checkpoints

            a, b = src.split(":")[1:]
            soup = OUT / "soups" / f"{name}.pt"
            if not soup.is_file():
                soup.parent.mkdir(parents=True, exist_ok=True)
                average_checkpoints(
                    [(OUT / "runs" / a / "last.pt", 0.5), (OUT / "runs" / b / "last.pt", 0.5)], soup
                )
            checkpoint = str(soup)
        else:
            checkpoint = src
        key = f"{name}_fit{args.fit}" if args.fit is not None else name
        entry = {
            "what": what + (f"; test-time fit, {args.fit} iterations" if args.fit else ""),
            **score(key, checkpoint, args.draws, args.fit),
            "scored": time.strftime("%Y-%m-%d"),
            "seconds": round(time.time() - t0),
        }
        table = (
            json.loads(JSON.read_text()) if JSON.is_file() else {}
        )  # rows scored meanwhile by another process
        table[key] = entry
        JSON.parent.mkdir(parents=True, exist_ok=True)
        JSON.write_text(json.dumps(table, indent=1))
        t = entry["transfer"]
        print(
            f"[movenet] {key}: real {100 * t['real_pck@0.1']['ours']:.1f} % / synthetic {100 * t['synthetic_pck@0.1']['ours']:.1f} %, "
            f"ratio {t['ratio@0.1']:.2f} ({t['ratio_90'][0]:.2f} to {t['ratio_90'][1]:.2f})"
            + (f", PA-MPJPE {entry['test']['pa_mpjpe_mm']:.1f} mm" if "test" in entry else ""),
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
