"""Markerless scan keypoints with MediaPipe on held-out Anny stand-in scans (docs/markerless.md):
the detector's failure rate per view and per keypoint, and the triangulated keypoints' 3D error
against the true BLSM keypoints, for plain scans and scans with a stool, missing feet, floor markers.

    python experiments/registration/markerless_keypoints.py --make        # the scans (out/markerless/*, about 1 min)
    python experiments/registration/markerless_keypoints.py               # the measurement (about 15 s per scan)

Writes ``out/markerless/results.json`` (every scan), ``docs/figures/markerless_keypoints.json``
(the summary), ``docs/figures/markerless_views.png`` (views with the detections drawn) and
``out/markerless/sheet_*.png`` (full-size sheets). Needs ``.venv-reference`` (scripts/setup_reference.sh).
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
OUT = ROOT / "out" / "markerless"
SEED = 3201  # held out: the project's populations use seeds 0-2
GROUPS = {
    "plain": {},
    "stool": {"stool": True},
    "missing_feet": {"missing_feet": True},
    "floor_markers": {"floor_markers": 8},
    "all_props": {"stool": True, "floor_markers": 8, "missing_feet": True},
}
PLAIN_SUBJECTS = 10  # rest + one pose each: 20 scans; the artefact groups use the first 3 subjects


def make_scans() -> None:
    from blsm.learn.scans.population import Artefacts, make_population

    for name, kw in GROUPS.items():
        n = PLAIN_SUBJECTS if name == "plain" else 3
        make_population(OUT / name, n, n, 1, seed=SEED, test_fraction=1.0, overwrite=True, artefacts=Artefacts(**kw))
    # A scan without a person: the stool and floor markers of a scan, alone.
    from blsm.learn.scans.format import Scan, load_scan, save_scan

    s = load_scan(OUT / "all_props" / "scans" / "s00000_01.npz")
    start = s.meta["props"]["stool"][0]
    keep = (s.faces >= start).all(1)
    save_scan(Scan(s.vertices[start:], s.faces[keep] - start, [], np.zeros((0, 3), np.float32),
                   {"id": "no_person"}, colors=s.colors[start:]), OUT / "no_person.npz")


def body_rotation(scan) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(scan.gt_global_orient.astype(np.float64)).as_matrix()


def measure_group(name: str, model, cfg, sheets: list[str]) -> list[dict]:
    from blsm.learn.markerless import keypoints as M
    from blsm.learn.scans.format import load_scan
    from blsm.learn.scans.population import read_population
    from blsm.pose2d.detectors import MediaPipeDetector

    folder = OUT / name
    rels = [r for s in read_population(folder)["subjects"] for r in s["scans"]]
    rows = []
    for rel in rels:
        scan = load_scan(folder / rel)
        t0 = time.time()
        res = M.scan_keypoints(scan, MediaPipeDetector(), cfg, where=str(folder / rel), keep_images=True)
        sec = time.time() - t0
        truth = M.true_keypoints(scan, model)
        err = res.points - truth  # (K, 3) world
        body = err @ body_rotation(scan)  # (K, 3) in the body's frame: x left, y up, z front
        vis = res.per_view.detections[..., 2][:, M._MP_INDEX] >= cfg.min_visibility  # (C, K)
        rows.append({
            "scan": f"{name}/{rel}", "pose": scan.meta["pose"], "seconds": round(sec, 1),
            "views": res.views, "views_with_person": res.views_with_person,
            "swapped": int(res.per_view.swapped.sum()),
            "detected": vis[res.per_view.found].sum(0).tolist(),
            "error_mm": [None if not np.isfinite(e).all() else round(float(np.linalg.norm(e)) * 1000, 2) for e in err],
            "body_error_mm": [None if not np.isfinite(e).all() else [round(float(x) * 1000, 2) for x in e] for e in body],
            "confidence": [round(float(c), 3) for c in res.confidence],
            "num_views": res.num_views.tolist(),
        })
        print(f"{name}/{rel}: {res.views_with_person}/{res.views} views, {res.per_view.swapped.sum()} swapped, "
              f"mean {np.nanmean(np.linalg.norm(err, axis=1)) * 1000:.1f} mm, {sec:.1f} s", flush=True)
        if f"{name}/{rel}" in sheets:
            M.contact_sheet(res.images, res, OUT / f"sheet_{name}_{Path(rel).stem}.png")
            sheets[sheets.index(f"{name}/{rel}")] = (res.images, res)
    return rows


def summarise(rows: list[dict], names: list[str]) -> dict:
    err = np.array([[np.nan if e is None else e for e in r["error_mm"]] for r in rows])  # (S, K)
    views = sum(r["views"] for r in rows)
    with_person = sum(r["views_with_person"] for r in rows)
    det = np.array([r["detected"] for r in rows]).sum(0) / max(with_person, 1)
    out = {
        "scans": len(rows),
        "views": views,
        "view_failure_rate": round(1 - with_person / views, 4),
        "swapped_views": sum(r["swapped"] for r in rows),
        "seconds_per_scan": round(float(np.mean([r["seconds"] for r in rows])), 1),
        "mean_mm_all": round(float(np.nanmean(err)), 1),
        "keypoints": {},
    }
    for k, n in enumerate(names):
        e = err[:, k]
        ok = np.isfinite(e)
        out["keypoints"][n] = {
            "detected_per_view_with_person": round(float(det[k]), 3),
            "triangulated": round(float(ok.mean()), 3),
            "mean_mm": round(float(e[ok].mean()), 1) if ok.any() else None,
            "p90_mm": round(float(np.percentile(e[ok], 90)), 1) if ok.any() else None,
        }
    return out


def bias_table(rows: list[dict], names: list[str]) -> dict:
    """Per keypoint the mean error vector in the body's frame (x left, y up, z front) and the spread
    about it: the detector's systematic offset from the BLSM keypoint, and what is left."""
    out = {}
    for k, n in enumerate(names):
        v = np.array([r["body_error_mm"][k] for r in rows if r["body_error_mm"][k] is not None])
        if len(v) < 3:
            continue
        mean = v.mean(0)
        out[n] = {"offset_mm": [round(float(x), 1) for x in mean], "offset_norm_mm": round(float(np.linalg.norm(mean)), 1),
                  "spread_mm": round(float(np.sqrt(((v - mean) ** 2).sum(1).mean())), 1)}
    return out


def no_person_check() -> dict:
    """``blsm scan-keypoints`` on a scan without a person: exit status and stderr."""
    res = subprocess.run([sys.executable, "-m", "blsm.cli", "scan-keypoints", str(OUT / "no_person.npz"),
                          "--out", str(OUT / "no_person.json")], capture_output=True, text=True, cwd=ROOT)
    lines = [ln for ln in res.stderr.splitlines() if "Warp" not in ln and ln.strip() and not ln.startswith(" ")]
    return {"exit": res.returncode, "stderr": lines[-1:] if lines else [], "wrote_output": (OUT / "no_person.json").exists()}


def save_figure(picks: list, path: Path, views: list[int]) -> None:
    from PIL import Image

    from blsm.learn.markerless.keypoints import contact_sheet

    tiles = []
    for images, res in picks:
        p = OUT / "_tmp_sheet.png"
        contact_sheet(images, res, p, views=views, cols=len(views))
        tiles.append(np.asarray(Image.open(p)))
        p.unlink()
    sheet = Image.fromarray(np.concatenate(tiles, 0))
    sheet = sheet.resize((sheet.width // 2, sheet.height // 2), Image.LANCZOS)
    from blsm.render import save_png

    save_png(np.asarray(sheet), path)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--make", action="store_true", help="make the scans first")
    ap.add_argument("--groups", default=",".join(GROUPS))
    args = ap.parse_args()
    if args.make:
        make_scans()
    import blsm
    from blsm.learn.markerless import keypoints as M

    model = blsm.load()
    cfg = M.MarkerlessConfig()
    sheets = ["plain/scans/s00001_01.npz", "stool/scans/s00000_01.npz", "missing_feet/scans/s00002_01.npz"]
    results, summary = {}, {}
    for g in args.groups.split(","):
        results[g] = measure_group(g, model, cfg, sheets)
        summary[g] = summarise(results[g], list(M.BLSM_NAMES))
    summary["bias_plain"] = bias_table(results.get("plain", []), list(M.BLSM_NAMES))
    summary["no_person"] = no_person_check()
    summary["config"] = {"views": cfg.views.views, "resolution": cfg.views.resolution, "fov_deg": cfg.views.fov_deg,
                         "focal_px": round(cfg.views.resolution / 2 / np.tan(np.radians(cfg.views.fov_deg) / 2), 1),
                         "min_visibility": cfg.min_visibility, "elevation_deg": [cfg.views.min_elevation_deg,
                                                                                  cfg.views.max_elevation_deg]}
    (OUT / "results.json").write_text(json.dumps({"summary": summary, "scans": results}, indent=1))
    (ROOT / "docs" / "figures" / "markerless_keypoints.json").write_text(json.dumps(summary, indent=1))
    picks = [s for s in sheets if not isinstance(s, str)]
    if picks:
        save_figure(picks, ROOT / "docs" / "figures" / "markerless_views.png", [0, 3, 7, 10, 14, 17])
    print(json.dumps({g: {k: v for k, v in s.items() if k != "keypoints"} for g, s in summary.items()
                      if isinstance(s, dict) and "scans" in s}, indent=1))
    print("no person:", summary["no_person"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
