"""The acceptance check of the video generator (docs/video.md, "Check"): every camera path made,
validated and drawn; contact against the field's velocity rule on walking clips.

1. For each camera path of :data:`synth.camera_paths.PATHS`: ``--sequences`` sequences of
   ``configs/synth/video.yaml`` with only that path (its weight 1, the others 0), into
   ``OUT/paths/<path>`` (each path with its own seed, the config's plus its number, so that the
   paths show other people, clips and backgrounds); ``synth validate`` on it; a contact sheet (``<path>_sheet.png``) and a
   preview (``<path>.png``, an animated PNG) of its first sequence in ``OUT``.
2. Contact on walking clips: ``--walks`` sequences of the CMU walking clips (subject 7, 007_01 to
   007_11) under a static camera, rendered small (contact does not depend on the image); per
   foot region (heels, toes) and frame, the exact contact against the velocity rule, their
   agreement, and where they differ, the cases (near the ground but moving: the heel strike and
   toe-off; still but above the ground).

    python experiments/video/video_check.py [--out out/video_check] [--doc docs/figures/video_check.json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
WALKS = [f"007_{i:02d}" for i in range(1, 12)]


def _run(cmd: list[str]) -> str:
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)}: exit {r.returncode}\n{r.stderr[-2000:]}")
    return (r.stdout.strip() or r.stderr.strip()).splitlines()[-1]


def _docs(dataset: Path) -> list[dict]:
    """Every sample's labels in key order (:meth:`synth.dataset.index.DatasetIndex.json`)."""
    from synth.dataset.index import DatasetIndex

    index = DatasetIndex(dataset)
    try:
        return [index.json(i) for i in range(len(index))]
    finally:
        index.close()


FIELD_RULES = {
    # name: (heel point, toe point, difference, threshold m/s): the contact rules of the methods users
    # train, on the joints they use (SMPL's ankle and foot joints; here BLSM's ankle joint and the toe
    # base, synth.sequence.toe_base), beside the labels' own.
    "the labels' rule (heel, toe base; central; 0.3 m/s)": ("heel", "toe_base", "central", 0.3),
    "the labels' rule until 2026-11-28 (heel, toe tip; central; 0.3 m/s)": ("heel", "toe_tip", "central", 0.3),
    "WHAM (ankle, toe base; central; 1 cm/frame)": ("ankle", "toe_base", "central", 0.3),
    "GVHMR (ankle, toe base; forward; 0.25 m/s)": ("ankle", "toe_base", "forward", 0.25),
    "HuMoR threshold (ankle, toe base; forward; 0.15 m/s)": ("ankle", "toe_base", "forward", 0.15),
}


def field_rules(dataset: Path, docs: list[dict]) -> dict:
    """The exact contact of the heels and toes against each rule of :data:`FIELD_RULES`, on the
    frames with both neighbours (the labels hold no frame outside a sequence): agreement per region
    and frame. The toe base comes from the rebuilt bodies (:class:`synth.validate.MeshRebuilder`)."""
    from synth.sequence import FEET, toe_base
    from synth.validate import MeshRebuilder

    cfg = json.loads((dataset / "manifest.json").read_text()).get("config", {})
    rebuild = MeshRebuilder(dataset, cfg)
    names = docs[0]["keypoint_names"]
    T, fps = docs[0]["frames"], docs[0]["fps"]
    pts: dict[str, list] = {k: [] for k in ("heel", "toe_tip", "ankle", "toe_base")}
    for i, d in enumerate(docs):
        v, _, kp = rebuild.mesh(d["people"][0])
        if i % T == 0:  # the toe base's vertices, fixed at the sequence's first frame (as the generator)
            base = toe_base(rebuild.model, rebuild.bones, v, kp)
        for k in ("heel", "toe_tip", "ankle"):
            pts[k].append([kp[names.index(f"{k}_{s}")] for s in ("l", "r")])
        pts["toe_base"].append([v[base[f"toe_{s}"]].mean(0) for s in ("l", "r")])
    arr = {k: np.asarray(x).reshape(-1, T, 2, 3) for k, x in pts.items()}  # (sequences, T, side, 3)
    exact = np.array([[d["people"][0]["contact"][r] for r in FEET] for d in docs]).reshape(-1, T, 4)[:, 1:-1]
    out = {}
    for name, (heel, toe, diff, thr) in FIELD_RULES.items():
        x = np.concatenate([arr[heel], arr[toe]], axis=2)  # (S, T, 4, 3): heel_l, heel_r, toe_l, toe_r
        if diff == "central":
            speed = np.linalg.norm(x[:, 2:] - x[:, :-2], axis=-1) * fps / 2
        else:  # frame t's speed from t to t + 1, as GVHMR's mask
            speed = np.linalg.norm(x[:, 2:] - x[:, 1:-1], axis=-1) * fps
        rule = speed < thr
        agree = rule == exact
        out[name] = {
            "agreement_region_frames": round(float(agree.mean()), 4),
            "per_region": {r: round(float(agree[..., i].mean()), 4) for i, r in enumerate(FEET)},
            "exact_only": int((exact & ~rule).sum()), "rule_only": int((~exact & rule).sum()),
            "contact_rate_rule": round(float(rule.mean()), 3),
        }
        print(f"[video_check] {name}: agreement {out[name]['agreement_region_frames']:.4f} "
              f"(exact only {out[name]['exact_only']}, rule only {out[name]['rule_only']})", flush=True)
    return {"frames_scored": int(exact.shape[0] * exact.shape[1]), "rules": out}


def paths(args: argparse.Namespace) -> dict:
    from synth.camera_paths import PATHS

    synth = str(Path(sys.executable).with_name("synth"))
    rows = {}
    from synth.config import load_config

    seed = load_config(args.config).seed
    for i, kind in enumerate(PATHS):
        out = args.out / "paths" / kind
        # Each path its own seed: other people, clips and backgrounds than the other paths'.
        sets = [f"sequence.cameras.{k}={1.0 if k == kind else 0.0}" for k in PATHS] + [f"seed={seed + i}"]
        t0 = time.time()
        _run([synth, "generate", args.config, "--out", str(out), "--num", str(args.sequences), "--workers", str(args.workers),
              "--resume", *sum((["--set", s] for s in sets + list(args.set)), [])])
        made = time.time() - t0
        line = _run([synth, "validate", str(out)])
        _run([synth, "preview", str(out), "--sequence", "0", "--video", str(args.out / f"{kind}.png"),
              "--sheet", str(args.out / f"{kind}_sheet.png"), "--count", "8"])
        docs = _docs(out)
        rows[kind] = {"validate": line, "frames": len(docs), "seconds": round(made, 1), "seed": seed + i,
                      "people": len(docs[0]["people"]), "clips": sorted({p["motion"]["clip"] for p in docs[0]["people"]}),
                      "in_view": round(float(np.mean([p["in_view"] for d in docs for p in d["people"]])), 3),
                      "path": docs[0]["camera"]["path"]}  # fmt: skip
        print(f"[video_check] {kind}: {line}; {len(docs)} frames in {made:.0f} s", flush=True)
    return rows


def walks(args: argparse.Namespace) -> dict:
    from synth.camera_paths import PATHS
    from synth.sequence import FEET

    synth = str(Path(sys.executable).with_name("synth"))
    out = args.out / "walks"
    sets = ["camera.width=64", "camera.height=64", "render.spp=1", "people.max=1", "hair.enabled=false",
            f"poses.clips={json.dumps(WALKS)}", "poses.exclude_clips=[]",
            *[f"sequence.cameras.{k}={1.0 if k == 'static' else 0.0}" for k in
              PATHS]]  # fmt: skip
    _run([synth, "generate", args.config, "--out", str(out), "--num", str(args.walks), "--workers", str(args.workers),
          "--resume", *sum((["--set", s] for s in sets), [])])
    docs = _docs(out)
    exact = np.array([[d["people"][0]["contact"][r] for r in FEET] for d in docs])
    rule = np.array([[d["people"][0]["contact_velocity"][r] for r in FEET] for d in docs])
    agree = exact == rule
    frames_agree = agree.all(1)
    # Where they differ: next to a change of either label (a heel strike, a toe-off) or not.
    T = docs[0]["frames"]
    near = np.zeros_like(agree)
    near_one = np.zeros_like(agree)
    for a in range(0, len(docs), T):
        e, r = exact[a:a + T], rule[a:a + T]
        change = np.zeros_like(e)
        flip = (e[1:] != e[:-1]) | (r[1:] != r[:-1])
        change[1:] |= flip
        change[:-1] |= flip
        near[a:a + T] = change
        rp, rn = np.vstack([r[:1], r[:-1]]), np.vstack([r[1:], r[-1:]])
        near_one[a:a + T] = (e == r) | (e == rp) | (e == rn)
    res = {
        "clips": sorted({d["people"][0]["motion"]["clip"] for d in docs}),
        "frames": len(docs),
        "region_frames": int(agree.size),
        "agreement_region_frames": round(float(agree.mean()), 4),
        "agreement_frames_all_four": round(float(frames_agree.mean()), 4),
        "exact_only": int((exact & ~rule).sum()),
        "rule_only": int((~exact & rule).sum()),
        "contact_rate_exact": round(float(exact.mean()), 3),
        "contact_rate_rule": round(float(rule.mean()), 3),
        "per_region": {r: round(float(agree[:, i].mean()), 4) for i, r in enumerate(FEET)},
        "agreement_within_one_frame": round(float(near_one.mean()), 4),
        "differ_next_to_a_change": round(float(near[~agree].mean()), 4) if (~agree).any() else None,
        "agreement_away_from_changes": round(float(agree[~near].mean()), 4),
    }
    print(f"[video_check] walks: {json.dumps(res)}", flush=True)
    res["field_rules"] = field_rules(out, docs)
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/synth/video.yaml")
    ap.add_argument("--out", type=Path, default=Path("out/video_check"))
    ap.add_argument("--doc", type=Path, help="write the results (JSON) here")
    ap.add_argument("--sequences", type=int, default=1, help="sequences per camera path")
    ap.add_argument("--walks", type=int, default=12, help="walking sequences for the contact check")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="overrides of the path runs")
    ap.add_argument("--skip-paths", action="store_true")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    res = {"config": args.config, "overrides": args.set}
    if not args.skip_paths:
        res["paths"] = paths(args)
    res["walks"] = walks(args)
    if args.doc and args.skip_paths and args.doc.exists():  # keep the path rows of an earlier run
        res["paths"] = json.loads(args.doc.read_text()).get("paths")
    if args.doc:
        args.doc.write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
