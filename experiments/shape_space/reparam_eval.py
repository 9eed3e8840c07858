"""Thesis Sec. 3.4 on our data: the original and the reparameterised BLSM on held-out registrations.

    python experiments/shape_space/reparam_eval.py --registrations out/shared_regs/registrations \\
        --population out/shared_regs/population --out-dir out/reparam \\
        --json docs/figures/reparam_eval.json --md docs/figures/reparam_eval.md

Makes the reparameterised models (``--schemes loop,midpoint``: the packaged template subdivided
once, 7002 -> 28002 vertices), brings the held-out rest-pose registrations (and the true bodies
under them, the scans' ``gt_points``) to the T-pose frame as ``blsm learn`` does
(:func:`blsm.learn.reparam.evaluate.tpose_instances`), and measures compactness, generalisation and
specificity (Figs. 3.2-3.4) of the original shape space, of the new model's (``mapped``: ``W P_s``)
and of Eq. 3.5's (``eq35``), for two readings of the held-out set in the new topology:

- ``registrations``: the unposed held-out registrations mapped by W' (the thesis' test set was
  aligned to the new template independently; this reading is not: it shares W with the model);
- ``truth``: the true bodies (Anny, ``gt_points``) unposed, and in the new topology *subdivided by
  the template's own scheme* (trimesh's Loop on each body), which does not use W at all.

Then the posed check (Sec. 3.4.2) of each new model. Timings on the 2-core machine: ~10 minutes.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

KS = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64)


def load_held_out(reg_dir: Path, population: Path, max_n: int):
    """Held-out rest-pose registrations: (files, vertices (N, V, 3), gt (N, V, 3), init dict)."""
    from blsm.learn.registration.registrations import load_registration
    from blsm.learn.training.train import is_rest_pose

    index = json.loads((population / "index.json").read_text())
    split = {s["id"]: s["split"] for s in index["subjects"]}
    rows = []
    for f in sorted(reg_dir.glob("*.npz")):
        reg = load_registration(f)
        if split.get(reg.meta.get("subject")) != "test" or not is_rest_pose(reg.meta):
            continue
        with np.load(population / "scans" / f"{reg.meta.get('scan', f.stem)}.npz") as z:
            gt = np.asarray(z["gt_points"], np.float32)
        rows.append((f.name, reg, gt))
    rows = rows[:max_n] if max_n > 0 else rows
    if not rows:
        raise SystemExit(f"{reg_dir}: no held-out rest-pose registrations")
    regs = [r for _, r, _ in rows]
    init = {k: torch.as_tensor(np.stack([getattr(r, k) for r in regs])) for k in ("angles", "global_orient", "transl")}
    return [n for n, _, _ in rows], torch.as_tensor(np.stack([r.vertices for r in regs])), \
        torch.as_tensor(np.stack([g for _, _, g in rows])), init


def curves(space, x, ks, samples, device, resample=None):
    """The four curves of ``space`` on instances ``x``; with ``resample`` (W') only generalisation and
    specificity, measured at the new topology's vertices."""
    from blsm.learn.reparam.evaluate import compactness, data_compactness, generalisation, specificity

    ks = [k for k in ks if k <= len(space.variances)]
    out = {"ks": ks, "generalisation_mm": generalisation(space, x, ks, resample).tolist(),
           "specificity_mm": specificity(space, x, ks, samples=samples, resample=resample, device=device).tolist()}
    if resample is None:
        comp = compactness(space)
        out.update(compactness=[float(comp[k - 1]) for k in ks], data_compactness=data_compactness(space, x, ks).tolist())
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default=None, help="model file (default: the packaged one)")
    ap.add_argument("--registrations", type=Path, default=ROOT / "out/shared_regs/registrations")
    ap.add_argument("--population", type=Path, default=ROOT / "out/shared_regs/population")
    ap.add_argument("--out-dir", type=Path, default=ROOT / "out/reparam")
    ap.add_argument("--schemes", default="loop,midpoint")
    ap.add_argument("--samples", type=int, default=1000, help="specificity samples (thesis: 1000)")
    ap.add_argument("--max-test", type=int, default=0, help="0 = every held-out rest-pose registration")
    ap.add_argument("--poses", type=int, default=16, help="random poses of the posed check")
    ap.add_argument("--device", default="cpu", help="torch device of the fits and the specificity (cuda for speed)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--md", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(2)

    import trimesh

    import blsm
    from blsm import io
    from blsm.learn.reparam.evaluate import posed_check, tpose_instances
    from blsm.learn.reparam.mapping import apply_rows, shape_space_eq35, shape_space_pca, sparse_rows
    from blsm.learn.reparam.model import (
        ReparamConfig,
        read_correspondence,
        reparameterise,
        subdivide_template,
    )
    from blsm.model import DEFAULT_MODEL

    t0 = time.perf_counter()
    src = Path(args.model) if args.model else DEFAULT_MODEL
    data = io.read_model(src)
    model1 = blsm.load(src)
    names, verts, gt, init = load_held_out(args.registrations, args.population, args.max_test)
    x1_reg, _, fit_reg = tpose_instances(model1, verts, init, device=args.device)
    x1_gt, _, fit_gt = tpose_instances(model1, gt, init, device=args.device)
    print(f"{len(names)} held-out rest-pose registrations; fit to registrations {fit_reg:.2f} mm, "
          f"to the true bodies {fit_gt:.2f} mm ({time.perf_counter() - t0:.0f} s)", flush=True)
    a = data.arrays
    mu1, p1, f1 = np.asarray(a["template"], np.float64), np.asarray(a["shape_basis"], np.float64), a["faces"]
    res = {"model": str(src), "held_out": names, "ks": list(KS), "samples": args.samples,
           "fit_mm": {"registrations": fit_reg, "truth": fit_gt}, "original": {}, "schemes": {}}
    orig = shape_space_pca(mu1, p1)
    x1 = {"registrations": x1_reg, "truth": x1_gt}
    for reading, x in x1.items():
        res["original"][reading] = curves(orig, x, KS, args.samples, args.device)
    for scheme in args.schemes.split(","):
        v2, f2 = subdivide_template(mu1, f1, 1, scheme)
        out = args.out_dir / f"{scheme}1.npz"
        new, rep = reparameterise(data, v2, f2, ReparamConfig())
        io.save_model(new, out)
        corners, bary = read_correspondence(out)
        m2 = blsm.load(out)
        wp = sparse_rows(corners, bary, len(mu1))
        mu2 = np.asarray(new.arrays["template"], np.float64)
        spaces = {"mapped": shape_space_pca(mu2, np.asarray(new.arrays["shape_basis"], np.float64)),
                  "eq35": shape_space_eq35(wp, mu1, p1, mu2)}
        x2 = {"registrations": np.stack([apply_rows(wp, x) for x in x1_reg]),
              "truth": np.stack([subdivide_template(x, f1, 1, scheme)[0] for x in x1_gt])}
        old_mesh, new_mesh = trimesh.Trimesh(mu1, f1, process=False), trimesh.Trimesh(mu2, f2, process=False)
        sres = {"file": str(out), "vertices": len(mu2), "coverage": rep["coverage"], "uv": rep["uv"],
                "volume_change": float(new_mesh.volume / old_mesh.volume - 1.0),
                "eq35_last_variance_m2": float(spaces["eq35"].variances[-1]),
                "posed": posed_check(model1, m2, corners, np.asarray(bary), np.load(out)["reparam_distance"],
                                     num=args.poses, surface=True)}
        for name, space in spaces.items():
            sres[name] = {reading: curves(space, x2[reading], KS, args.samples, args.device) for reading in x2}
        sres["original_at_new"] = {r: curves(orig, x1[r], KS, args.samples, args.device, wp) for r in x1}
        res["schemes"][scheme] = sres
        print(f"{scheme}: done ({time.perf_counter() - t0:.0f} s)", flush=True)
    res["seconds"] = round(time.perf_counter() - t0, 1)
    md = report(res)
    print(md)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(res, indent=1))
    if args.md:
        args.md.write_text("<!-- written by experiments/shape_space/reparam_eval.py -->\n" + md)
    return 0


def report(res: dict) -> str:
    """Markdown tables: each curve for the original and every new space, and the worst ratio."""
    lines = []
    metrics = (("compactness", "compactness (model variance in the first k)", "{:.4f}"),
               ("data_compactness", "held-out variance in the first k", "{:.4f}"),
               ("generalisation_mm", "generalisation (mm)", "{:.3f}"),
               ("specificity_mm", "specificity (mm)", "{:.3f}"))
    for reading in ("truth", "registrations"):
        for key, title, fmt in metrics:
            cols = [("original", res["original"][reading])]
            for scheme, s in res["schemes"].items():
                if key in s["original_at_new"][reading]:
                    cols.append((f"original at {scheme} vertices", s["original_at_new"][reading]))
                cols += [(f"{scheme} {n}", s[n][reading]) for n in ("mapped", "eq35")]
            ks = cols[0][1]["ks"]
            lines += [f"\n**{title}, held-out {reading}**\n", "| k | " + " | ".join(c for c, _ in cols) + " |",
                      "|---:|" + "---:|" * len(cols)]
            for i, k in enumerate(ks):
                lines.append(f"| {k} | " + " | ".join(fmt.format(c[key][i]) if i < len(c[key]) else "" for _, c in cols) + " |")
            worst = []
            for scheme in res["schemes"]:
                base = dict(cols)[f"original at {scheme} vertices"] if f"original at {scheme} vertices" in dict(cols) else cols[0][1]
                for n in ("mapped", "eq35"):
                    c = dict(cols)[f"{scheme} {n}"]
                    r = [abs(c[key][i] / base[key][i] - 1) for i in range(min(len(ks), len(c[key]))) if base[key][i] > 0]
                    worst.append(f"{scheme} {n} {100 * max(r):.2f} %")
            ref = "the original measured at the same vertices" if key in ("generalisation_mm", "specificity_mm") else "the original"
            lines.append(f"\nlargest relative difference over k from {ref}: {', '.join(worst)}")
    lines.append("\n**posed check** (mm; new posed vertices against W' times the old posed ones)\n")
    lines.append("| template | poses | vertices within 0.1 mm of the old surface | mean | 99th pct | max | "
                 "to old posed surface: mean | max | all vertices: mean | max |")
    lines.append("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for scheme, s in res["schemes"].items():
        p = s["posed"]
        lines.append(f"| {scheme} | {p['poses']} | {p['coinciding_vertices']} of {s['vertices']} | "
                     f"{p['coinciding_mean_mm']:.3f} | {p['coinciding_p99_mm']:.3f} | {p['coinciding_max_mm']:.2f} | "
                     f"{p['coinciding_surface_mean_mm']:.3f} | {p['coinciding_surface_max_mm']:.2f} | "
                     f"{p['all_mean_mm']:.3f} | {p['all_max_mm']:.2f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
