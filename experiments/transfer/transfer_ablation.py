"""The transfer ablation of docs/transfer.md: one row per lever, each at the same training budget.

    python experiments/transfer/transfer_ablation.py [--rows base plates ...] [--docs docs]

Each row fine-tunes the packaged HMR-BLSM on one lever's data with one recipe
(configs/recovery/transfer/ROW.yaml; the data of configs/synth/transfer/DATA.yaml is made first
when missing), then scores the run's ``last.pt``:

- ``recovery evaluate`` on the held-out synthetic test set ``out/data/test`` (configs/synth/test.yaml:
  held-out subjects, CMU clips 007_12 and 005_20, the sunset.exr background): PA-MPJPE;
- ``recovery transfer`` on the real development set (scripts/setup_transfer_devset.py) against
  MediaPipe Pose, with the same synthetic test set: the transfer ratio.

The row ``packaged`` scores the packaged checkpoint itself (no fine-tuning). Every step is resumable
(a finished step is skipped), so an interrupted run continues. Results go to ``docs/figures/transfer.json``
and the table between the markers of ``docs/transfer.md``; rows not run now keep their entries of
that file, so ``--rows X`` adds or updates row X only.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from blsm.io import sha256_file  # noqa: E402

BIN = Path(sys.executable).parent
TEST = "out/data/test"
REAL = "out/transfer_dev"
ROWS = {  # name: (lever, data configs, recovery config)
    "packaged": ("the 9000-step network (packaged until 2026-11-27; every fine-tuning row starts from it), not fine-tuned", (), None),
    "base": ("fine-tuned on the base data (procedural sky; the protocol's reference row)", ("base",), "base"),
    "plates": ("backgrounds: real photographs as backplates, horizon-aligned", ("plates",), "plates"),
    "effects": ("camera and sensor effects, occluders (data.effects)", ("base",), "effects"),
    "truncation": ("close-ups that cut the person (data.effects.truncation_prob 0.5)", ("base",), "truncation"),
    "recipe": ("recipe: backbone at 0.1x the rate, frozen BatchNorm statistics", ("base",), "recipe"),
    "combined": ("every lever: backplates, effects, close-ups, recipe", ("plates",), "combined"),
    "garments": ("clothing geometry: garments as meshes over the body (synth.garments)", ("garments",), "garments"),
    "occluders": ("occlusion: objects in front of the people in the scene (synth.occluders)", ("occluders",), "occluders"),
    "detail": ("skin, face and hand detail: eyes, brows, lips, facial hair, pores, knuckles (subjects.detail)", ("detail",), "detail"),
    "crop192": ("crop size 192 instead of 128 (the packaged weights fine-tuned and scored at 192 px)", ("base",), "crop192"),
    "imagenet_lite0": ("backbone pair, EfficientNet-Lite0 from ImageNet (not the packaged weights), 128 px", ("base",), "imagenet_lite0"),
    "imagenet_lite2": ("backbone pair, EfficientNet-Lite2 from ImageNet (not the packaged weights), 128 px", ("base",), "imagenet_lite2"),
    "imagenet_frozen": ("backbone frozen at its ImageNet weights (Lite0; rate 0, BatchNorm frozen), only the regressor learns", ("base",), "imagenet_frozen"),
    "augment_strong": ("augmentation strength: looser boxes, harsher colour (data.augment)", ("base",), "augment_strong"),
    "garments_effects": ("clothing geometry and the camera, sensor and occlusion effects together", ("garments",), "garments_effects"),
    "randconv": ("style: half of the crops restyled by a random convolution (RandConv; data.effects.randconv_prob)", ("base",), "randconv"),
    "fda": ("style: half of the crops given a real photograph's low-frequency spectrum (FDA; data.effects.fda_prob)", ("base",), "fda"),
    "subjects": ("people: 240 Anny subjects instead of 24 (each seen about 10 times, not 100)", ("subjects",), "subjects"),
    "postures": ("postures: people seated on box seats, arms over their full range (synth.postures)", ("postures",), "postures"),
    "garments_effects_postures": ("garments_effects with postures: people seated on box seats, arms over their full range (synth.postures)",
                                  ("garments_postures",), "garments_effects_postures"),
    "garments_effects_subjects": ("garments_effects on data with 240 Anny subjects instead of 24 (the subjects lever)",
                                  ("garments_subjects",), "garments_effects_subjects"),
    "plates_crowd": ("backgrounds with crowds: backplates, 3 to 5 people an image instead of 1 to 2", ("plates_crowd",),
                     "plates_crowd"),
    "garments_effects_subjects_seed1": ("garments_effects_subjects again with train.seed 1 (data order, augmentation, dropout): "
                                        "the spread between runs of one recipe", ("garments_subjects",), "garments_effects_subjects_seed1"),
    "garments_effects_subjects_seed2": ("garments_effects_subjects again with train.seed 2", ("garments_subjects",),
                                        "garments_effects_subjects_seed2"),
    "garments_effects_subjects_1202": ("garments_effects_subjects trained and scored again on 2026-12-02, with antialiased crops "
                                       "(the frontal row's reference)", ("garments_subjects",), "garments_effects_subjects_1202"),
    "garments_effects_subjects_frontal": ("views as photographs show people: garments_effects_subjects with half of the cameras "
                                          "within 45 degrees of the first person's front (camera.frontal_rate 0.5)",
                                          ("garments_subjects_frontal",), "garments_effects_subjects_frontal"),
    "gpu_imagenet_lite0": ("backbone pair at the packaged crop budget: EfficientNet-Lite0 from ImageNet, 288k crops of the subjects data (GPU)",
                           ("subjects",), "gpu_imagenet_lite0"),
    "gpu_imagenet_lite2": ("backbone pair at the packaged crop budget: EfficientNet-Lite2 from ImageNet, 288k crops of the subjects data (GPU)",
                           ("subjects",), "gpu_imagenet_lite2"),
    "default": ("the packaged checkpoint since 2026-11-27: garments_effects_subjects and the 9000-step network, "
                "weights averaged half and half (WiSE-FT)", (), None),
}
# Rows trained on a lent GPU by experiments/transfer/gpu_backbones.py: their exported checkpoint is put
# at out/transfer/runs/ROW/last.pt by hand and only scored here.
GPU_ROWS = ("gpu_imagenet_lite0", "gpu_imagenet_lite2")
# The network every fine-tuning row starts from (``train.init`` of configs/recovery/transfer/*.yaml): the
# 9000-step HMR-BLSM of configs/recovery/hmr_blsm_lite0.yaml, packaged until 2026-11-27 and kept in the
# repository's history (make recovery-model makes it again).
BASE_WEIGHTS = "out/weights/hmr_blsm_lite0_9000.pt"
BASE_REVISION, BASE_PATH = "57d2400", "recovery/weights/hmr_blsm_default.pt"
BASE_SHA256 = "cee4143ba259dd6fab034679f184fbc33fd70b4b7f124c9a4409508b418476e0"
BEGIN, END = "<!-- transfer-ablation:begin -->", "<!-- transfer-ablation:end -->"


def run(cmd: list[str], log: Path) -> float:
    """Run ``cmd`` from the repository root, its output appended to ``log``; returns seconds."""
    t = time.time()
    with log.open("a") as fh:
        fh.write(f"$ {' '.join(cmd)}\n")
        fh.flush()
        res = subprocess.run(cmd, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT)
    if res.returncode != 0:
        raise SystemExit(f"transfer_ablation: {' '.join(cmd)} failed (exit {res.returncode}); see {log}")
    return time.time() - t


def base_weights() -> str:
    """``BASE_WEIGHTS``: the file there (made by make recovery-model), else the one in the repository's
    history (checked by its SHA-256)."""
    path = ROOT / BASE_WEIGHTS
    if not path.is_file():
        blob = subprocess.run(["git", "show", f"{BASE_REVISION}:{BASE_PATH}"], cwd=ROOT, capture_output=True)
        if blob.returncode != 0:
            raise SystemExit(f"transfer_ablation: {path}: missing and not in this checkout's history "
                             "(make recovery-model makes it)")
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_bytes(blob.stdout)
        if sha256_file(tmp) != BASE_SHA256:
            tmp.unlink()
            raise SystemExit(f"transfer_ablation: {BASE_REVISION}:{BASE_PATH}: not the 9000-step network (SHA-256 differs)")
        tmp.replace(path)
    return str(path)


def checkpoint_of(name: str, out: Path) -> str:
    """The checkpoint a row scores: its run's last.pt, the 9000-step network, or the packaged one."""
    if name == "packaged":
        return base_weights()
    return "default" if name == "default" else str(out / "runs" / name / "last.pt")


def score(ck: str, ev: Path, tr: Path, log: Path, seconds: dict[str, float]) -> tuple[dict, dict]:
    """``recovery evaluate`` of checkpoint ``ck`` on the test set into ``ev`` and ``recovery transfer``
    on the development set into ``tr`` (each skipped when done; its time into ``seconds``); returns
    the metrics and the transfer report."""
    if not (ev / "metrics.json").is_file():
        seconds["evaluate"] = run([str(BIN / "recovery"), "evaluate", ck, TEST, "--out", str(ev)], log)
    if not (tr / "report.json").is_file():
        seconds["transfer"] = run([str(BIN / "recovery"), "transfer", ck, "--real", REAL, "--synthetic", TEST,
                                   "--out", str(tr)], log)
    return json.loads((ev / "metrics.json").read_text()), json.loads((tr / "report.json").read_text())


def summary(metrics: dict, rep: dict) -> dict:
    """A scored network's headline numbers (:func:`score`'s results), as the weight averages and the
    budget runs record them."""
    real, syn = rep["domains"]["real"]["pck@0.1"], rep["domains"]["synthetic"]["pck@0.1"]
    return {"pa_mpjpe_mm": metrics["pa_mpjpe_mm"], "real_pck@0.1": real["ours"], "synthetic_pck@0.1": syn["ours"],
            "transfer_ratio@0.1": rep["transfer_ratio@0.1"], "transfer_ratio_90": rep.get("transfer_ratio_90")}


def headline(s: dict) -> str:
    """:func:`summary` in one line."""
    return (f"PA-MPJPE {s['pa_mpjpe_mm']:.1f} mm, PCK@0.1 real {100 * s['real_pck@0.1']:.1f} %, "
            f"synthetic {100 * s['synthetic_pck@0.1']:.1f} %, transfer ratio {s['transfer_ratio@0.1']:.2f}")


def row(name: str, out: Path, log: Path) -> dict:
    lever, data, config = ROWS[name]
    result = out / "results" / f"{name}.json"
    if result.is_file():
        return json.loads(result.read_text())
    runs = out / "runs" / name
    if name in GPU_ROWS and not (runs / "last.pt").is_file():
        raise SystemExit(f"transfer_ablation: {runs / 'last.pt'}: row {name} trains on a GPU; run "
                         "experiments/transfer/gpu_backbones.py there and put its exported file here")
    seconds: dict[str, float] = {}
    for d in () if name in GPU_ROWS else data:  # a GPU row's data were carried there as its crop cache
        if not (ROOT / "out/transfer/data" / d / "manifest.json").is_file():
            seconds[f"data_{d}"] = run([str(BIN / "synth"), "generate", f"configs/synth/transfer/{d}.yaml",
                                        "--out", f"out/transfer/data/{d}", "--workers", "2", "--resume"], log)
    ck = checkpoint_of(name, out)
    if config and name not in GPU_ROWS and not ((runs / "last.pt").is_file() and (runs / "done").is_file()):
        base_weights()  # the run's train.init
        seconds["train"] = run([str(BIN / "recovery"), "train", f"configs/recovery/transfer/{config}.yaml",
                                "--out", str(runs), "--resume"], log)
        (runs / "done").write_text("")
    metrics, rep = score(ck, out / "eval" / name, out / "check" / name, log, seconds)
    res = {"row": name, "lever": lever, "data": list(data), "config": f"configs/recovery/transfer/{config}.yaml" if config else None,
           "checkpoint": ck, "pa_mpjpe_mm": metrics["pa_mpjpe_mm"], "mpjpe_mm": metrics["mpjpe_mm"],
           "test_people": metrics["people"], "transfer": rep, "seconds": seconds}
    result.parent.mkdir(parents=True, exist_ok=True)
    result.write_text(json.dumps(res, indent=1))
    return res


def table(results: list[dict]) -> str:
    lines = ["| row | lever | PA-MPJPE synthetic test (mm) | PCK@0.1 real: ours / floor | PCK@0.1 synthetic: ours / floor | "
             "transfer ratio @0.1 (90 % interval) | @0.2 | one floor: PCK@0.1 real floor / ratio |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        t = r["transfer"]
        real, syn = t["domains"]["real"]["pck@0.1"], t["domains"]["synthetic"]["pck@0.1"]
        ci = t.get("transfer_ratio_90")
        ci_text = f" ({ci[0]:.2f} to {ci[1]:.2f})" if ci else ""
        one = (f"{100 * real['synthetic_floor']:.1f} % / {t['transfer_ratio_synthetic_floor@0.1']:.2f}"
               if "synthetic_floor" in real else "-")  # checks made before the second reading: none
        lines.append(f"| `{r['row']}` | {r['lever']} | {r['pa_mpjpe_mm']:.1f} | {100 * real['ours']:.1f} / {100 * real['floor']:.1f} % | "
                     f"{100 * syn['ours']:.1f} / {100 * syn['floor']:.1f} % | {t['transfer_ratio@0.1']:.2f}{ci_text} | "
                     f"{t['transfer_ratio@0.2']:.2f} | {one} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", nargs="+", default=[r for r in ROWS if r not in GPU_ROWS], choices=list(ROWS),
                    help="rows to run (default: every row but the GPU rows, which are only scored when named)")
    ap.add_argument("--out", default="out/transfer")
    ap.add_argument("--docs", default="docs")
    args = ap.parse_args()
    out = ROOT / args.out
    out.mkdir(parents=True, exist_ok=True)
    log = out / "ablation.log"
    results = []
    for name in args.rows:
        print(f"[transfer] {name}: {ROWS[name][0]}", flush=True)
        results.append(row(name, out, log))
        r = results[-1]
        print(f"[transfer] {name}: PA-MPJPE {r['pa_mpjpe_mm']:.1f} mm, transfer ratio {r['transfer']['transfer_ratio@0.1']:.2f}", flush=True)
    docs = ROOT / args.docs
    (docs / "figures").mkdir(parents=True, exist_ok=True)
    figure = docs / "figures" / "transfer.json"
    kept = {r["row"]: r for r in (json.loads(figure.read_text()) if figure.is_file() else []) if r["row"] in ROWS}
    kept.update({r["row"]: r for r in results})
    results = [kept[n] for n in ROWS if n in kept]  # the table in ROWS order
    figure.write_text(json.dumps(results, indent=1))
    md = docs / "transfer.md"
    text = md.read_text() if md.is_file() else f"{BEGIN}\n{END}\n"
    if BEGIN in text and END in text:
        head, rest = text.split(BEGIN, 1)
        text = head + BEGIN + "\n" + table(results) + "\n" + END + rest.split(END, 1)[1]
        md.write_text(text)
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
