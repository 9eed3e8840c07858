"""Thesis Table 4.2 / 4.3 on our data (docs/recovery_ablation.md; ``make recovery-ablation``).

    python experiments/recovery_ablation/ablation.py CONFIG_DIR --test DATASET --out DIR [--docs docs]

One resumable run: trains the mesh autoencoder (``autoencoder.yaml``) and reports it against
PCA on held-out meshes, then trains Configs A-F (``A.yaml`` ... ``F.yaml``; D and F load the
autoencoder), evaluates each run's last checkpoint on the test set (``recovery evaluate``: the same
people for all), and writes

- ``docs/figures/recovery_ablation.json``: ``{"configs": {"A": {"joint_mm", "vertex_mm", "pa_joint_mm",
  ...}, ...}, "autoencoder": {"vertex_mm", "pca_vertex_mm", ...}}`` (errors in the body frame, the
  global rotation removed, as thesis Table 4.3; the camera-frame metrics of ``recovery evaluate``
  alongside);
- ``docs/recovery_ablation.md``: the table, the thesis' claims checked, budgets and the split;
- ``docs/figures/recovery_ablation_C_vs_A.png`` and ``..._E_vs_B.png`` (thesis Figs. 4.5, 4.6) and
  ``docs/figures/recovery_ablation_roughness.png`` (every config's meshes of the same people, coloured by
  the length of the uniform Laplacian: spikes show).

Every stage is skipped when its output is complete (a finished run, an evaluation of the same
checkpoint step), so re-running after an interruption continues where it stopped. Bad input (a
missing config, no test dataset) is one line ``ablation: error: ...`` and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from blsm.io import atomic_write  # noqa: E402

CONFIGS = ("A", "B", "C", "D", "E", "F")
THESIS = {  # Table 4.3 (Human3.6M, mm)
    "A": {"joint_mm": 96.37, "vertex_mm": 109.10}, "B": {"joint_mm": 88.75, "vertex_mm": 100.83},
    "C": {"joint_mm": 88.62, "vertex_mm": 95.08}, "D": {"joint_mm": 90.66, "vertex_mm": 102.44},
    "E": {"joint_mm": 81.76, "vertex_mm": 93.69}, "F": {"joint_mm": 85.76, "vertex_mm": 96.34},
}


def _run_done(run: Path, steps: int) -> bool:
    from recovery.checkpoint import read_checkpoint

    last = run / "last.pt"
    return last.is_file() and int(read_checkpoint(last)["step"]) >= steps


def train_stage(config: Path, run: Path, log: Any = print) -> float:
    """Train (or continue) one run to its end; returns the wall time of the whole run (s, from its log)."""
    from recovery.config import load_config
    from recovery.train import train
    from recovery.trainer import read_log

    cfg = load_config(config)
    if not _run_done(run, cfg.train.steps):
        log(f"[ablation] training {config.name} -> {run}")
        if train(cfg, run, resume=True, log=log) != "done":
            raise KeyboardInterrupt
    recs = [r for r in read_log(run / "log.jsonl") if r["kind"] == "train"]
    return train_seconds(recs)


def train_seconds(recs: list[dict[str, Any]]) -> float:
    """Sum of the logged intervals, leaving out gaps longer than 10 minutes (a run resumed later)."""
    t = [r["time"] for r in recs]
    gaps = np.diff(t) if len(t) > 1 else np.zeros(0)
    first = recs[0]["step"] if recs else 0
    per_step = float(np.median(gaps / np.maximum(np.diff([r["step"] for r in recs]), 1))) if len(gaps) else 0.0
    return float(gaps[gaps < 600].sum() + per_step * first)


def autoencoder_report(checkpoint: Path, config: Path, log: Any = print) -> dict[str, Any]:
    """Held-out mean vertex error (mm) of the autoencoder and of PCA with as many components as the
    latent code, fitted on training meshes of the same distribution (thesis Sec. 4.3.3)."""
    import blsm
    from recovery.checkpoint import read_checkpoint
    from recovery.config import load_config, model_file
    from recovery.datasets.meshes import MeshSource, describe, fixed_meshes
    from recovery.eval.metrics import vertex_error_mm
    from recovery.mesh.operators import mesh_operators
    from recovery.models.mesh_ae import MeshAutoencoder
    from recovery.models.pca import PCAModel

    cfg = load_config(config)
    path = model_file(cfg)
    body = blsm.load(path)
    ops = mesh_operators(path, cfg.mesh.cache, cfg.mesh.ops_settings(), log=log)
    ck = read_checkpoint(checkpoint)
    state = ck["modules"]["ae"]
    ae = MeshAutoencoder(ops, state["normalizer.mean"], state["normalizer.std"], tuple(cfg.mesh.channels), cfg.mesh.latent)
    ae.load_state_dict(state)
    ae.eval()
    m = cfg.meshes
    test_src, train_src = MeshSource(body, m, "test"), MeshSource(body, m, "train")
    prior_src = MeshSource(body, m, "test", poses="prior")
    test = fixed_meshes(body, test_src, m.test_meshes, seed=cfg.train.seed + 3)
    test_prior = fixed_meshes(body, prior_src, m.test_meshes, seed=cfg.train.seed + 5)
    train = fixed_meshes(body, train_src, m.pca_meshes, seed=cfg.train.seed + 4)
    t0 = time.perf_counter()
    pca = PCAModel.fit(train, m.pca_components)
    log(f"[ablation] PCA-{m.pca_components} on {len(train)} meshes: {time.perf_counter() - t0:.1f} s")

    def ae_mm(meshes: torch.Tensor) -> torch.Tensor:
        return torch.cat([vertex_error_mm(ae.reconstruct(v), v) for v in meshes.split(64)])

    with torch.no_grad():
        ae_err, pca_err = ae_mm(test), vertex_error_mm(pca.reconstruct(test), test)
        ae_prior, pca_prior = ae_mm(test_prior), vertex_error_mm(pca.reconstruct(test_prior), test_prior)
        train_ae = ae_mm(train[:1000])
        train_pca = vertex_error_mm(pca.reconstruct(train[:1000]), train[:1000])
        ks = sorted({k for k in (8, 16, 32, 64, 128) if k < m.pca_components} | {m.pca_components})
        curve = {str(k): [float(vertex_error_mm(pca.truncated(k).reconstruct(t), t).mean()) for t in (test, test_prior)]
                 for k in ks}
        spread = float(vertex_error_mm(test.mean(0, keepdim=True).expand_as(test), test).mean())
    return {
        "vertex_mm": float(ae_err.mean()), "pca_vertex_mm": float(pca_err.mean()),
        "vertex_mm_median": float(ae_err.median()), "pca_vertex_mm_median": float(pca_err.median()),
        "prior_vertex_mm": float(ae_prior.mean()), "prior_pca_vertex_mm": float(pca_prior.mean()),
        "train_vertex_mm": float(train_ae.mean()), "train_pca_vertex_mm": float(train_pca.mean()),
        "pca_by_components": curve, "test_mean_mesh_mm": spread,
        "test_meshes": len(test), "pca_train_meshes": len(train), "pca_components": m.pca_components,
        "latent": cfg.mesh.latent, "parameters": int(sum(p.numel() for p in ae.parameters())),
        "steps": int(ck["step"]), "batch_size": cfg.train.batch_size, "sizes": ops.sizes,
        "test_split": describe(test_src), "prior_split": describe(prior_src), "train_split": describe(train_src),
        "checkpoint": str(checkpoint),
    }


def evaluate_stage(run: Path, dataset: Path, log: Any = print) -> dict[str, Any]:
    """``recovery evaluate`` of the run's last checkpoint (skipped when done for the same step)."""
    from recovery.checkpoint import read_checkpoint
    from recovery.eval.evaluate import evaluate

    out = run / "eval"
    step = int(read_checkpoint(run / "last.pt")["step"])
    path = out / "metrics.json"
    if path.is_file():
        res = json.loads(path.read_text())
        if res.get("step") == step and res.get("dataset") == str(dataset):
            return res
    log(f"[ablation] evaluating {run / 'last.pt'} on {dataset}")
    res = evaluate(run / "last.pt", dataset, out, log=log)
    res["step"] = step
    with atomic_write(path, "w") as fh:
        fh.write(json.dumps(res, indent=1))
    return res


def _people(dataset: Path, count: int, crop: int) -> list[dict[str, Any]]:
    from recovery.datasets.sampling import spread_indices
    from synth.dataset.images import SynthDataset

    ds = SynthDataset(dataset, crop=crop, box_scale=1.2)
    return [ds[int(i)] for i in spread_indices(len(ds), count)]


def _predict(checkpoint: Path, people: list[dict[str, Any]]) -> Any:
    from recovery.predictor import load_predictor

    pr = load_predictor(checkpoint, log=lambda *a: None)
    images = torch.stack([p["image"] for p in people])
    k = torch.stack([torch.as_tensor(p["K_crop"]).float() for p in people])
    return pr, pr(images, k)


def comparison_sheet(runs: dict[str, Path], people: list[dict[str, Any]], png: Path, title: str) -> None:
    """Thesis Figs. 4.5 / 4.6: per person the crop, then per config the mesh overlay and a side view
    (prediction blue, labels grey)."""
    from PIL import Image, ImageDraw

    from recovery.models.hmr import body_outputs
    from recovery.utils.viz import overlay, side_view

    preds = {name: _predict(run / "last.pt", people) for name, run in runs.items()}
    body = next(iter(preds.values()))[0].body
    faces = body.faces.numpy()
    cell = 160
    rows = []
    for i, p in enumerate(people):
        img = (p["image"].permute(1, 2, 0).numpy() * 255 + 0.5).clip(0, 255).astype(np.uint8)
        k = np.asarray(p["K_crop"], np.float64)
        with torch.no_grad():
            gt = body_outputs(body, torch.as_tensor(p["pose"])[None], torch.as_tensor(p["global_orient"])[None],
                              torch.as_tensor(p["bone"])[None], torch.as_tensor(p["shape"])[None])
        gv = (gt.vertices[0] + torch.as_tensor(p["transl_cam"])).numpy()
        cols = [img]
        for name, (_, pred) in preds.items():
            v = (pred.vertices[i] + pred.transl[i]).numpy()
            cols += [overlay(img, v, faces, k), side_view([(v, (0.35, 0.55, 0.95)), (gv, (0.7, 0.7, 0.7))], faces, img.shape[0])]
        row = Image.new("RGB", (cell * len(cols), cell), "white")
        for c, im in enumerate(cols):
            row.paste(Image.fromarray(im).resize((cell, cell), Image.BILINEAR), (c * cell, 0))
        rows.append(row)
    head = Image.new("RGB", (rows[0].width, 18), "white")
    labels = "crop | " + " | ".join(f"{n}: mesh, side (blue) vs labels (grey)" for n in runs)
    ImageDraw.Draw(head).text((3, 3), f"{title}   {labels}", fill="black")
    sheet = Image.new("RGB", (rows[0].width, 18 + cell * len(rows)), "white")
    sheet.paste(head, (0, 0))
    for r, row in enumerate(rows):
        sheet.paste(row, (0, 18 + r * cell))
    png.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(png)


def roughness_sheet(runs: dict[str, Path], people: list[dict[str, Any]], png: Path) -> None:
    """Every config's body-frame meshes of the same people (front view, upright), faces coloured by
    how much longer their uniform Laplacian is than on the labels' mesh of that person (0 to 10 mm,
    white to red: spikes show red), with the labels' meshes first; each row's label is its mean
    Laplacian length."""
    from PIL import Image, ImageDraw

    from blsm.mesh import uniform_laplacian_matrix
    from recovery.datasets.meshes import body_frame_vertices
    from recovery.utils.geometry import UPRIGHT_FACING_CAMERA
    from recovery.utils.viz import side_view

    preds = {name: _predict(run / "last.pt", people) for name, run in runs.items()}
    body = next(iter(preds.values()))[0].body
    faces = body.faces.numpy()
    lap = uniform_laplacian_matrix(faces, body.num_vertices)
    with torch.no_grad():
        labels = body_frame_vertices(body, torch.stack([torch.as_tensor(p["pose"]) for p in people]),
                                     torch.stack([torch.as_tensor(p["bone"]) for p in people]),
                                     torch.stack([torch.as_tensor(p["shape"]) for p in people]))
    rows_v = {"labels": labels, **{n: pred.body_vertices for n, (_, pred) in preds.items()}}
    cell = 200
    up = UPRIGHT_FACING_CAMERA.numpy()
    sheet = Image.new("RGB", (cell * len(people) + 90, cell * len(rows_v)), "white")
    draw = ImageDraw.Draw(sheet)
    def lap_mm(verts: torch.Tensor) -> np.ndarray:
        return torch.stack([torch.sparse.mm(lap, v.float()).norm(dim=-1) for v in verts]).numpy() * 1000  # (B, V)

    base = lap_mm(labels)
    for r, (name, verts) in enumerate(rows_v.items()):
        rough = lap_mm(verts)
        draw.text((4, r * cell + cell // 2 - 12), f"{name}\n{rough.mean():.2f} mm", fill="black")
        for i in range(len(people)):
            t = np.clip((rough[i] - base[i])[faces].mean(1) / 10.0, 0, 1)
            col = np.stack([np.ones_like(t), 1 - t, 1 - t], 1) * 0.9
            im = side_view([(verts[i].numpy() @ up.T, col)], faces, cell, yaw_deg=0.0)
            sheet.paste(Image.fromarray(im), (90 + i * cell, r * cell))
    png.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(png)


def run_ablation(config_dir: str | Path, test: str | Path, out: str | Path, docs: str | Path = "docs",
                 log: Any = print) -> dict[str, Any]:
    """Everything of the module docstring; returns the JSON written to ``docs/figures/recovery_ablation.json``."""
    from recovery.config import load_config

    config_dir, test, out, docs = Path(config_dir), Path(test), Path(out), Path(docs)
    for name in ("autoencoder", *CONFIGS):
        if not (config_dir / f"{name}.yaml").is_file():
            raise ValueError(f"{config_dir / (name + '.yaml')}: missing (the ablation needs autoencoder.yaml and A-F.yaml)")
    if not (test / "manifest.json").is_file():
        raise ValueError(f"{test / 'manifest.json'}: no test dataset here")
    result: dict[str, Any] = {"configs": {}, "test": str(test)}
    ae_run = out / "autoencoder"
    ae_seconds = train_stage(config_dir / "autoencoder.yaml", ae_run, log)
    ae_json = ae_run / "report.json"
    saved = json.loads(ae_json.read_text()) if ae_json.is_file() else {}
    if saved.get("steps") == load_config(config_dir / "autoencoder.yaml").train.steps and "prior_vertex_mm" in saved:
        ae = saved
    else:
        ae = autoencoder_report(ae_run / "last.pt", config_dir / "autoencoder.yaml", log)
        ae["train_minutes"] = ae_seconds / 60
        with atomic_write(ae_json, "w") as fh:
            fh.write(json.dumps(ae, indent=1))
    result["autoencoder"] = ae
    for name in CONFIGS:
        cfg_path = config_dir / f"{name}.yaml"
        seconds = train_stage(cfg_path, out / name, log)
        res = evaluate_stage(out / name, test, log)
        cfg = load_config(cfg_path)
        bf = res["body_frame"]
        result["configs"][name] = {
            "joint_mm": bf["joint_mm"], "vertex_mm": bf["vertex_mm"], "pa_joint_mm": bf["pa_joint_mm"],
            "roughness_mm": bf["roughness_mm"], "label_roughness_mm": bf["label_roughness_mm"],
            "camera_frame": {k: res[k] for k in ("mpjpe_mm", "pa_mpjpe_mm", "pve_mm", "pck_0.05", "pck_0.1")},
            "segmentation": res.get("segmentation"), "people": res["people"],
            "task": cfg.task, "steps": cfg.train.steps, "batch_size": cfg.train.batch_size, "lr": cfg.optim.lr,
            "train_minutes": seconds / 60, "thesis": THESIS[name],
        }
    people = _people(test, 6, load_config(config_dir / "A.yaml").data.crop)
    figures = docs / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    comparison_sheet({"A": out / "A", "C": out / "C"}, people, figures / "recovery_ablation_C_vs_A.png", "thesis Fig. 4.5: C (decoder) vs A (parameters)")
    comparison_sheet({"B": out / "B", "E": out / "E"}, people, figures / "recovery_ablation_E_vs_B.png", "thesis Fig. 4.6: E (decoder + BEGAN) vs B (HMR-BLSM)")
    roughness_sheet({n: out / n for n in CONFIGS}, people[:4], figures / "recovery_ablation_roughness.png")
    with atomic_write(figures / "recovery_ablation.json", "w") as fh:
        fh.write(json.dumps(result, indent=1))
    with atomic_write(docs / "recovery_ablation.md", "w") as fh:
        fh.write(report_markdown(result, config_dir, out, docs))
    return result


def claims(result: dict[str, Any]) -> list[tuple[str, bool, str]]:
    """The thesis' claims (Sec. 4.5.3) checked on our numbers: (claim, holds, the numbers)."""
    c = result["configs"]
    out = []
    for a, b, what in (("C", "A", "the mesh decoder beats parameter regression (C < A)"),
                       ("E", "C", "the BEGAN discriminator improves the decoder (E < C)"),
                       ("C", "B", "plain decoder regression is at least on par with HMR in vertices (C < B)"),
                       ("E", "B", "the proposed method beats HMR (E < B)")):
        va, vb = c[a]["vertex_mm"], c[b]["vertex_mm"]
        out.append((what, va < vb, f"vertex {va:.1f} vs {vb:.1f} mm; joints {c[a]['joint_mm']:.1f} vs {c[b]['joint_mm']:.1f} mm"))
    re_, rc = c["E"]["roughness_mm"], c["C"]["roughness_mm"]
    out.append(("the discriminator removes spiky surfaces (roughness E < C)", re_ < rc, f"roughness {re_:.2f} vs {rc:.2f} mm"))
    return out


def report_markdown(result: dict[str, Any], config_dir: Path, out: Path, docs: Path = Path("docs")) -> str:
    """The report; ``docs/figures/recovery_ablation_gpu.json`` (a GPU run) and ``docs/recovery_ablation_notes.md``
    (measured discussion) are included when present."""
    c, ae = result["configs"], result["autoencoder"]
    lines = [
        "# Thesis Table 4.3 on our data: HMR-BLSM, parameter regression and the spiral mesh decoder",
        "",
        f"Made by `python experiments/recovery_ablation/ablation.py {config_dir} --test {result['test']} --out {out}` "
        f"(resumable; configs in "
        f"`{config_dir}/`). Test set: `{result['test']}` — held-out subjects, the clips 007_12 / 005_20 and "
        "`sunset.exr` (docs/recovery.md, \"Split\"); the same people for every config. Errors in the **body frame** "
        "(global rotation removed, pelvis-aligned, as thesis Sec. 4.5.2), joints (the 17 evaluation joints) regressed "
        "from the predicted and the labels' meshes by the same keypoint regressor.",
        "",
        "| Config | network | joints (mm) | vertices (mm) | PA joints (mm) | roughness (mm; labels) | camera-frame PA-MPJPE | train (min) | thesis joints / vertices |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    names = {"A": "parameters", "B": "HMR-BLSM (IEF + 47-D D)", "C": "decoder", "D": "pretrained frozen decoder",
             "E": "decoder + BEGAN", "F": "pretrained decoder + pretrained BEGAN D"}
    for n, r in c.items():
        lines.append(f"| {n} | {names[n]} | {r['joint_mm']:.1f} | {r['vertex_mm']:.1f} | {r['pa_joint_mm']:.1f} | "
                     f"{r['roughness_mm']:.2f} ({r['label_roughness_mm']:.2f}) | {r['camera_frame']['pa_mpjpe_mm']:.1f} | "
                     f"{r['train_minutes']:.0f} | {r['thesis']['joint_mm']:.2f} / {r['thesis']['vertex_mm']:.2f} |")
    lines += ["", f"Budgets: every config {c['A']['steps']} steps of {c['A']['batch_size']} crops, generator Adam "
              f"{c['A'].get('lr', 0):g} with a cosine schedule (equal samples; the wall time differs and is listed).", "",
              "## The thesis' claims", ""]
    for what, holds, nums in claims(result):
        lines.append(f"- {what}: **{'holds' if holds else 'does not hold'}** ({nums})")
    lines += ["", "## Autoencoder against PCA", "",
              f"Held-out meshes ({ae['test_meshes']}: {ae['test_split']['people']} people never trained on, "
              f"{ae['test_split']['poses']}): autoencoder (latent {ae['latent']}, {ae['parameters']:,} parameters, "
              f"{ae['steps']} steps of {ae['batch_size']}, {ae.get('train_minutes', 0):.0f} min) **{ae['vertex_mm']:.2f} mm** mean vertex error "
              f"(median {ae['vertex_mm_median']:.2f}); PCA with {ae['pca_components']} components fitted on "
              f"{ae['pca_train_meshes']} training meshes **{ae['pca_vertex_mm']:.2f} mm** (median {ae['pca_vertex_mm_median']:.2f}). "
              f"The same people in {ae['test_meshes']} pose-prior draws (the prior's whole range, harder than the two clips): "
              f"autoencoder {ae['prior_vertex_mm']:.2f} mm, PCA {ae['prior_pca_vertex_mm']:.2f} mm. "
              f"On training meshes: {ae['train_vertex_mm']:.2f} vs {ae['train_pca_vertex_mm']:.2f} mm. "
              f"Every test mesh replaced by their mean: {ae['test_mean_mesh_mm']:.1f} mm.", "",
              f"- autoencoder at most PCA's error (held-out clips): **{'holds' if ae['vertex_mm'] <= ae['pca_vertex_mm'] else 'does not hold'}**",
              "", "PCA's held-out error by the number of components (mm; held-out clips / prior poses):", "",
              "| components | " + " | ".join(ae["pca_by_components"]) + " |",
              "|---|" + "---|" * len(ae["pca_by_components"]),
              "| clips | " + " | ".join(f"{v[0]:.2f}" for v in ae["pca_by_components"].values()) + " |",
              "| prior | " + " | ".join(f"{v[1]:.2f}" for v in ae["pca_by_components"].values()) + " |", ""]
    gpu = docs / "figures" / "recovery_ablation_gpu.json"
    if gpu.is_file():
        lines += ["## On a GPU", ""]
        for g in json.loads(gpu.read_text())["runs"]:
            curve = ", ".join(f"{v} mm at step {k}" for k, v in g["val_vertex_mm"].items())
            text = (f"- Latent {g['latent']}: `{g['command']}` ({g['config']}: batch {g['batch_size']}, {g['planned_steps']} "
                    f"steps planned) on {g['device']}: {g['steps_reached']} steps in {g['train_seconds']:.0f} s "
                    f"({g['meshes_per_second']:.0f} meshes/s); validation ({g['val_split']}): {curve}. Status: {g['status']}.")
            r = g.get("report")
            if r:
                text += (f" Held-out clips: autoencoder **{r['vertex_mm']:.2f} mm** (median {r['vertex_mm_median']:.2f}), "
                         f"PCA-{r['pca_components']} **{r['pca_vertex_mm']:.2f} mm** (median {r['pca_vertex_mm_median']:.2f}); "
                         f"prior poses {r['prior_vertex_mm']:.2f} vs {r['prior_pca_vertex_mm']:.2f} mm; training meshes "
                         f"{r['train_vertex_mm']:.2f} vs {r['train_pca_vertex_mm']:.2f} mm.")
            lines.append(text)
        lines.append("")
    notes = docs / "recovery_ablation_notes.md"
    if notes.is_file():
        lines += [notes.read_text().rstrip(), ""]
    fig = "[`{0}`](figures/{0})".format
    lines += [f"Figures: {fig('recovery_ablation_C_vs_A.png')} (Fig. 4.5), {fig('recovery_ablation_E_vs_B.png')} "
              f"(Fig. 4.6), {fig('recovery_ablation_roughness.png')} (every config's meshes of the same people, "
              "faces coloured by the uniform Laplacian's length).", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """The command line of the module docstring; returns the exit status."""
    ap = argparse.ArgumentParser(description="thesis Table 4.3 on our data: autoencoder vs PCA, Configs A-F (resumable)")
    ap.add_argument("configs", help="folder with autoencoder.yaml and A.yaml ... F.yaml")
    ap.add_argument("--test", required=True, help="the test dataset folder")
    ap.add_argument("--out", required=True, help="run folder (one sub-folder per config)")
    ap.add_argument("--docs", default="docs", help="where recovery_ablation.md goes (its JSON and figures under figures/)")
    args = ap.parse_args(argv)
    from recovery.cli import error_line

    try:
        run_ablation(args.configs, args.test, args.out, args.docs)
    except (ValueError, FloatingPointError) as exc:
        print(f"ablation: error: {error_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("ablation: interrupted; run the same command to continue", file=sys.stderr)
        return 130
    print(f"wrote {args.docs}/recovery_ablation.md and {args.docs}/figures/recovery_ablation.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
