"""LEAP on BLSM measured for docs/leap.md (issue 55, parts 1-2): Table 2 (IoU and Chamfer on unseen
poses and unseen subjects) for each run given (the Fig. 4 ablation: with and without the cycle
distance), the learning curves, the cost per query beside the exact tests', and a figure of
reconstructed bodies beside the true meshes.

    python experiments/leap/measure.py out/leap/cpu out/leap/cpu_nocycle --chamfer 20 \\
        --json docs/figures/leap.json --figure docs/figures/leap_bodies.png --curve docs/figures/leap_curve.png
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

import blsm
from blsm import occupancy
from blsm.leap.mesh import chamfer, grid_box, reconstruct, true_meshes
from blsm.leap.model import Leap
from blsm.leap.train import evaluate, load_run

SPLITS = ("unseen_poses", "unseen_subjects")
ABOUT = {
    "split": "unseen poses: training subjects (9 of every 10 population rows) in held-out clips (every 8th of the imported "
             "CMU library, sorted); unseen subjects: every 10th population row in training clips",
    "iou_protocol": "iou: the paper's (the authors' evaluation scores the uniform points only: uniform in the body's box grown "
                    "by 10 %); iou_near: the points within N(0, 1 cm^2) of the surface; iou_all: both; mean over bodies; ground "
                    "truth the exact winding number",
    "chamfer": "symmetric mean surface distance (mm) between 10,000 points on each surface, LEAP's by marching cubes of the "
               "0.5 level on a grid over the body's grown box",
}


def table(leap: Leap, data: dict, model: torch.nn.Module, n_chamfer: int, res: int) -> dict:
    out = {}
    faces = model.faces.numpy()
    for split in SPLITS:
        r = evaluate(leap, data, split)
        n = min(n_chamfer, len(data[f"{split}_B"]))
        verts = true_meshes(model, data[f"{split}_B"][:n], data[f"{split}_subject"][:n])
        rng = np.random.default_rng(0)
        cd = [chamfer(reconstruct(leap, data[f"{split}_B"][i], *grid_box(verts[i]), res), (verts[i], faces), 10000, rng)
              for i in range(n)]  # fmt: skip
        r.update({"chamfer_mm": round(1000.0 * float(np.mean(cd)), 2), "chamfer_bodies": n, "grid": res})
        out[split] = r
    return out


def _time(fn, *args, rounds: int = 3) -> tuple[float, object]:
    """The best of ``rounds`` wall times of ``fn(*args)``, and its last answer."""
    best, out = np.inf, None
    for _ in range(rounds):
        t0 = time.perf_counter()
        out = fn(*args)
        best = min(best, time.perf_counter() - t0)
    return best, out


def _encode(leap: Leap, Bt: torch.Tensor) -> tuple:
    body = leap.body(Bt)  # once a body: the features both encoders read
    return leap.codes(body), leap.lbs_conditions(body)


def cost(leap: Leap, data: dict, model: torch.nn.Module, n: int = 100000) -> dict:
    """Per-body set-up and per-query time of LEAP and of the exact tests on one unseen-pose body and
    ``n`` query points drawn as the training points; each answer's agreement with the exact one (the
    timed calls' own answers)."""
    faces = model.faces.numpy()
    B = data["unseen_poses_B"][:1]
    verts = true_meshes(model, B, data["unseen_poses_subject"][:1])[0]
    pts = occupancy.sample_points(verts, faces, n // 2, n - n // 2, np.random.default_rng(1))
    truth = occupancy.inside(pts, verts, faces)
    rows = {}
    few = pts[:1000]
    for name, fn in (("exact winding number", lambda p: occupancy.inside(p, verts, faces)),
                     ("fast winding number", lambda p: occupancy.inside(p, verts, faces, exact=False))):  # fmt: skip
        (t_all, ans), (t_few, _) = _time(fn, pts), _time(fn, few)
        per = (t_all - t_few) / (len(pts) - len(few))
        rows[name] = {"setup_ms": round(1000 * (t_few - per * len(few)), 1), "setup": "every call",
                      "per_query_us": round(1e6 * per, 2), "agree": float(np.mean(ans == truth))}
    t_build, sdf = _time(occupancy.MeshSDF, verts, faces)
    t_q, (dist, *_) = _time(sdf, pts)
    rows["MeshSDF"] = {"setup_ms": round(1000 * t_build, 1), "setup": "once a mesh", "per_query_us": round(1e6 * t_q / len(pts), 2),
                       "agree": float(np.mean((dist < 0) == truth))}
    Bt, x = torch.from_numpy(B), torch.from_numpy(pts.astype(np.float32))[None]
    with torch.no_grad():
        t_body, _ = _time(_encode, leap, Bt)
        t_all, out = _time(lambda: [leap(Bt, x[:, s : s + 65536]) for s in range(0, n, 65536)])
        pred = torch.cat([o["logits"][0] for o in out]).numpy() >= 0
    rows["LEAP (this run)"] = {"setup_ms": round(1000 * t_body, 1), "setup": "once a body (encoders)",
                               "per_query_us": round(1e6 * (t_all - t_body) / n, 2), "agree": float(np.mean(pred == truth))}
    return {"points": n, "torch_threads": torch.get_num_threads(), "mesh": f"BLSM, {len(verts)} vertices, {len(faces)} faces",
            "rows": rows}


def figure(leap: Leap, data: dict, model: torch.nn.Module, path: Path, per_split: int, res: int) -> None:
    from blsm.render import render_grid

    faces = model.faces.numpy()
    items, labels = [], []
    for split in SPLITS:
        verts = true_meshes(model, data[f"{split}_B"][:per_split], data[f"{split}_subject"][:per_split])
        for i in range(per_split):
            rec = reconstruct(leap, data[f"{split}_B"][i], *grid_box(verts[i]), res)
            items += [[(verts[i], faces)], [rec]]
            labels += [f"{split.replace('_', ' ')} {i}: true", "LEAP"]
    render_grid(items, path, labels=labels, cols=2 * per_split, tile_size=(160, 256), spp=8)


def extrapolate(points: list[dict], lbs_steps: int) -> dict:
    """What more stage-2 training would give, from the curve: ``iou = a - b s^-c`` (``s`` stage-2
    steps) fitted by least squares to each test set's points, read at 20k and 200k steps (the
    paper's length), with ``a`` the asymptote. A fit to a handful of points: an estimate."""
    from scipy.optimize import curve_fit

    out = {}
    for split in SPLITS:
        s = np.array([p["step"] - lbs_steps for p in points if p["step"] > lbs_steps], float)
        y = np.array([p[split] for p in points if p["step"] > lbs_steps], float)
        if len(s) < 4:
            continue
        f = lambda t, a, b, c: a - b * t ** (-c)  # noqa: E731
        try:
            (a, b, c), _ = curve_fit(f, s, y, p0=(y[-1] + 1.0, 10.0, 0.5), bounds=([0, 0, 0.01], [100, 1e6, 3]), maxfev=20000)
        except RuntimeError:
            continue
        out[split] = {"asymptote": round(float(a), 2), "at_20k": round(float(f(20000, a, b, c)), 2),
                      "at_200k": round(float(f(200000, a, b, c)), 2), "exponent": round(float(c), 3),
                      "fit_rms": round(float(np.sqrt(np.mean((f(s, a, b, c) - y) ** 2))), 3), "points": len(s)}
    return out


def curve(histories: dict[str, list], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    for name, hist in histories.items():
        pts = [h for h in hist if "eval" in h and h["stage"] == "occupancy"]  # stage 1 leaves ONet untrained
        for split, ls in zip(SPLITS, ("-", "--")):
            ax.plot([h["step"] for h in pts], [h["eval"][split]["iou"] for h in pts], ls, marker="o", label=f"{name}, {split.replace('_', ' ')}")
    ax.set_xlabel("step (stage 2 starts after stage 1's 3000)")
    ax.set_ylabel("IoU (%), uniform points")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--chamfer", type=int, default=20, help="bodies per test set for the Chamfer distance")
    ap.add_argument("--res", type=int, default=96, help="marching-cubes grid nodes per axis")
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--figure", type=Path)
    ap.add_argument("--curve", type=Path)
    args = ap.parse_args(argv)
    model = blsm.load()
    doc: dict = {"command": "python experiments/leap/measure.py " + " ".join(str(r) for r in args.runs)
                 + f" --chamfer {args.chamfer} --res {args.res}", **ABOUT, "runs": {}}
    histories = {}
    for i, run in enumerate(args.runs):
        leap, cfg, ck = load_run(run / "last.pt", model)
        with np.load(run / "data.npz") as d:
            data = {k: d[k] for k in d.files}
        name = "cycle" if cfg.net.cycle else "no cycle"
        histories[name] = ck["history"]
        doc["runs"][str(run)] = {"cycle": cfg.net.cycle, "step": ck["step"], **table(leap, data, model, args.chamfer, args.res),
                                 "curve": [{"step": h["step"], **{s: h["eval"][s]["iou"] for s in SPLITS}} for h in ck["history"] if "eval" in h]}
        doc["runs"][str(run)]["extrapolated"] = extrapolate(doc["runs"][str(run)]["curve"], cfg.lbs_steps)
        print(json.dumps(doc["runs"][str(run)], indent=1), flush=True)
        if i == 0:
            doc["held_out_clips"] = [str(c) for c in data["held_out_clips"]]
            doc["test_bodies"] = int(len(data["unseen_poses_B"]))
            doc["cost"] = cost(leap, data, model)
            print(json.dumps(doc["cost"], indent=1), flush=True)
            first = doc["runs"][str(run)]
            doc["iou_unseen_poses"], doc["iou_unseen_subjects"] = first["unseen_poses"]["iou"], first["unseen_subjects"]["iou"]
            if args.figure:
                figure(leap, data, model, args.figure, 3, args.res)
    if args.curve:
        curve(histories, args.curve)
    args.json.write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
