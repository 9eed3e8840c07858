"""Paper 000 Fig. 4 on our registrations: BLSM-linear, SMPL-reimpl and BLSM-spiral fitted to held-out
registrations against the number of coefficients (docs/blsm_spiral.md).

    python experiments/shape_space/blsm_spiral_fig4.py prepare --work W          # CPU: the mesh hierarchy (fast-simplification)
    python experiments/shape_space/blsm_spiral_fig4.py run --regs R --work W --device cuda  # learn, decoders, SMPL-reimpl, fits
    python experiments/shape_space/blsm_spiral_fig4.py report --work W --out docs/figures/blsm_spiral_fig4  # .png, .json; prints the tables

``run`` learns BLSM-linear once (``blsm learn``'s :func:`blsm.learn.training.train.learn_model`, the default
training config with 32 shape components) and keeps the T-pose residuals it learns the shape space
from; trains one spiral auto-decoder per latent size on those residuals (BLSM-spiral models share
everything else with BLSM-linear); trains SMPL-reimpl (``blsm train-smpl``'s
:func:`blsm.learn.evaluation.smpl_reimpl.train_smpl_reimpl`) on the same training split; then fits every model to
the rest-pose registration of every held-out subject (the staged fit plus Levenberg-Marquardt of
``blsm evaluate``). BLSM-spiral with latent size L is fitted with its 10 bone and L latent coefficients
free, so it is plotted at k = 10 + L, counted as BLSM-linear counts its bone and shape coefficients.
Diagnostics: the same fits on training subjects (train against held-out: over-fitting), the fit of
the training subjects with the shape held at the auto-decoder's own code (optimisation error), and
the residual-space errors of the auto-decoder and of the PCA with as many components.
Everything is written to ``W/fig4.json`` after each step.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import blsm  # noqa: E402
from blsm import io  # noqa: E402
from blsm.learn.evaluation.evaluate import EvalConfig, error_stats, fit_errors, shape_curve  # noqa: E402
from blsm.learn.evaluation.fit import BLSMFittable, FitConfig  # noqa: E402
from blsm.spiral.autodecoder import SpiralConfig, train_auto_decoder  # noqa: E402
from blsm.spiral.hierarchy import MeshOperators  # noqa: E402
from blsm.spiral.sampling import Level  # noqa: E402
from blsm.spiral.shape import decoder_arrays  # noqa: E402


def log(msg: str) -> None:
    print(f"[fig4 {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def save_ops(ops: MeshOperators, path: Path) -> None:
    arrays = {}
    for i, lv in enumerate(ops.levels):
        arrays.update({f"spiral_{i}": ops.spirals[i], f"down_{i}": lv.down, f"up_index_{i}": lv.up_index,
                       f"up_weight_{i}": lv.up_weight})
    np.savez(path, **arrays)


def load_ops(path: Path) -> MeshOperators:
    z = np.load(path)
    n = len([k for k in z.files if k.startswith("down_")])
    levels = [Level(down=z[f"down_{i}"], up_index=z[f"up_index_{i}"], up_weight=z[f"up_weight_{i}"],
                    faces=np.zeros((0, 3), np.int64)) for i in range(n)]
    nv = len(z["up_index_0"])
    return MeshOperators(levels=levels, spirals=[z[f"spiral_{i}"] for i in range(n)], faces=[],
                         reference=np.zeros((nv, 3), np.float32), regressor=np.zeros((0, nv), np.float32),
                         keypoint_names=[], regressor_error_mm=0.0, model_sha256="")


def cmd_prepare(args: argparse.Namespace) -> None:
    from blsm.spiral.hierarchy import body_hierarchy

    args.work.mkdir(parents=True, exist_ok=True)
    ops = body_hierarchy(blsm.load(args.model), SpiralConfig().settings())
    save_ops(ops, args.work / "ops.npz")
    log(f"hierarchy {ops.sizes} -> {args.work / 'ops.npz'}")
    if args.regs is not None:  # slim copies (free-form displacement zeroed: nothing here reads it) to carry
        out = args.work / "regs"
        out.mkdir(exist_ok=True)
        split = {}
        if args.population is not None:  # `blsm register` leaves split None: the population's index has it
            index = json.loads((args.population / "index.json").read_text())
            split = {sub["id"]: sub["split"] for sub in index["subjects"]}
        for f in sorted(args.regs.glob("*.npz")):
            with np.load(f) as z:
                arrays = {k: z[k] for k in z.files}
            arrays["displacement"] = np.zeros_like(arrays["displacement"])  # required by the reader, unused here
            meta = json.loads(str(arrays["meta"]))
            if meta.get("split") is None:
                meta["split"] = split[meta["subject"]]
            arrays["meta"] = np.array(json.dumps(meta))
            np.savez_compressed(out / f.name, **arrays)
        log(f"{len(list(out.glob('*.npz')))} registrations -> {out}")


def stats_dict(errors: torch.Tensor) -> dict:
    return asdict(error_stats(errors.cpu()))


class Results:
    """fig4.json, rewritten after every step."""

    def __init__(self, path: Path) -> None:
        self.path, self.data = path, {}

    def put(self, key: str, value) -> None:  # noqa: ANN001
        self.data[key] = value
        self.path.write_text(json.dumps(self.data, indent=1))


def first_per_subject(regs, limit: int = 0):  # noqa: ANN001, ANN201
    first: dict[str, int] = {}
    for i, s in enumerate(regs.subjects):
        first.setdefault(s, i)
    idx = sorted(first.values())
    return regs.select(idx[:limit] if limit else idx)


def learn_linear(args: argparse.Namespace, res: Results) -> tuple[io.ModelData, torch.Tensor, list[str]]:
    from blsm.learn.registration.registrations import load_registrations
    from blsm.learn.training.train import is_rest_pose, learn_model, load_train_config

    cfg = load_train_config(args.config)
    cfg = replace(cfg, device=args.learn_device or args.device, shape=replace(cfg.shape, num_coeffs=args.shape_coeffs))
    if args.quick:
        cfg = replace(cfg, fit=replace(cfg.fit, iterations=10), weights=replace(cfg.weights, iterations=5))
    regs = load_registrations([args.regs])
    keep: dict[str, torch.Tensor] = {}
    data, report = learn_model(blsm.load(args.model), regs, cfg, on_shape_residuals=lambda r: keep.update(r=r.detach()))
    rest_subjects = [str(r.meta.get("subject")) for r in regs if str(r.meta.get("split") or "train") == "train"
                     and is_rest_pose(r.meta)]
    io.save_model(data, args.work / "blsm_linear.npz")
    res.put("learn", {"errors_mm": report["errors_mm"], "registrations": report["registrations"],
                      "seconds": report["seconds"], "shape_pca_explained": report["shape_pca_explained"]})
    return data, keep["r"], rest_subjects


def pca_residual_error(data: io.ModelData, resid: torch.Tensor, k: int) -> float:
    """Training residuals projected on the first k PCA components (the linear space's own error), mm."""
    basis = torch.as_tensor(data.arrays["shape_basis"][:k], dtype=torch.float64).reshape(k, -1).to(resid.device)
    mean = resid.double().mean(0).reshape(-1)  # the PCA mean is in the template: residuals are centred
    x = resid.double().reshape(len(resid), -1) - mean
    coef = torch.linalg.lstsq(basis.T, x.T).solution.T
    err = (coef @ basis - x).reshape(len(resid), -1, 3).norm(dim=-1).mean() * 1000
    return float(err)


def train_spirals(args: argparse.Namespace, data: io.ModelData, resid: torch.Tensor, res: Results) -> dict[int, Path]:
    ops = load_ops(args.ops or args.work / "ops.npz")
    out, info = {}, {}
    for lat in args.latents:
        cfg = SpiralConfig(latent=lat, epochs=args.epochs, lr_decay=args.lr_decay)
        dec, codes, rep = train_auto_decoder(resid.to(args.device), ops, cfg, log_every=100)
        arrays, meta = decoder_arrays(dec, ops, codes, rep)
        d2 = copy.deepcopy(data)
        d2.arrays.update(arrays)
        d2.meta["shape_decoder"] = meta
        out[lat] = io.save_model(d2, args.work / f"blsm_spiral_{lat}.npz")
        info[str(lat)] = {"train_error_mm": rep["train_error_mm"], "pca_train_error_mm": pca_residual_error(data, resid, lat),
                          "seconds": rep["seconds"], "code_norm_mean": rep["code_norm_mean"],
                          "loss_curve_mm": rep["loss_curve_mm"]}
        log(f"spiral L={lat}: residual training error {rep['train_error_mm']:.3f} mm "
            f"(PCA with {lat}: {info[str(lat)]['pca_train_error_mm']:.3f} mm), {rep['seconds']} s")
        res.put("spiral", info)
    return out


def start_smpl(args: argparse.Namespace, src: Path):  # noqa: ANN201
    """``blsm train-smpl`` on the training split, in a CPU process beside the GPU work (its training has
    CPU-only steps), with the learnt BLSM-linear's skeleton and weights."""
    import os
    import subprocess

    cmd = [sys.executable, "-c", "import sys; from blsm.cli import main; sys.exit(main())", "train-smpl",
           "--model", str(src / "blsm_linear.npz"), "--registrations", str(args.regs),
           "--num-coeffs", str(args.smpl_coeffs), "--iterations", args.iterations,
           "--lm-iterations", str(args.lm_iterations), "--out", str(args.work / "smpl_reimpl.npz")]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parents[2]),
                                                         os.environ.get("PYTHONPATH", "")])}
    log("SMPL-reimpl: training on the CPU in the background")
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True), time.time()


def finish_smpl(args: argparse.Namespace, job, linear, res: Results):  # noqa: ANN001, ANN201
    """Wait for :func:`start_smpl`; the model on the linear model's device (None if it failed)."""
    from blsm.learn.evaluation.smpl_reimpl import load_smpl_reimpl

    proc, t0 = job
    out, _ = proc.communicate()
    res.put("smpl", {"returncode": proc.returncode, "seconds": round(time.time() - t0, 1), "output": out[-2000:]})
    log(f"SMPL-reimpl: exit {proc.returncode} after {time.time() - t0:.0f} s")
    if proc.returncode != 0:
        return None
    return load_smpl_reimpl(args.work / "smpl_reimpl.npz", linear)


def smpl_curve(args: argparse.Namespace, job, linear, res: Results, curve, test, src: Path) -> None:  # noqa: ANN001
    """SMPL-reimpl's held-out curve, once :func:`start_smpl` is done; on the CPU if the device fails."""
    from blsm.learn.evaluation.smpl_reimpl import SMPLReimplFittable, load_smpl_reimpl

    smpl = finish_smpl(args, job, linear, res)
    if smpl is None:
        return
    ks = [k for k in args.ks if k <= args.smpl_coeffs]
    try:
        curve("test", "SMPL-reimpl", SMPLReimplFittable(smpl.to(linear.template.device)), test, ks)
    except RuntimeError as exc:  # a device mix-up in the baseline: fit it on the CPU instead
        log(f"SMPL-reimpl on the device failed ({exc}); fitting on the CPU")
        cpu_smpl = load_smpl_reimpl(args.work / "smpl_reimpl.npz", blsm.load(src / "blsm_linear.npz"))
        test.vertices = test.vertices.cpu()
        curve("test", "SMPL-reimpl", SMPLReimplFittable(cpu_smpl), test, ks)


def cmd_run(args: argparse.Namespace) -> None:
    from blsm.learn.registration.registrations import load_registration_set

    args.work.mkdir(parents=True, exist_ok=True)
    res = Results(args.work / "fig4.json")
    res.put("settings", {k: str(v) for k, v in vars(args).items() if k != "func"})
    dev = torch.device(args.device)
    t0 = time.time()
    src = args.learnt or args.work
    if args.learnt is None:
        data, resid, rest_subjects = learn_linear(args, res)
        log(f"learnt BLSM-linear on {len(resid)} residuals in {time.time() - t0:.0f} s")
        if args.learn_only:
            torch.save({"residuals": resid.cpu(), "rest_subjects": rest_subjects}, args.work / "residuals.pt")
            return
    else:  # learnt before (e.g. on another machine): its model, residuals and numbers
        data = io.read_model(src / "blsm_linear.npz")
        saved = torch.load(src / "residuals.pt")
        resid, rest_subjects = saved["residuals"], saved["rest_subjects"]
        res.put("learn", json.loads((src / "fig4.json").read_text())["learn"])
    smpl_job = start_smpl(args, src)
    spiral_paths = train_spirals(args, data, resid, res)
    linear = blsm.load(src / "blsm_linear.npz").to(dev)
    kb = linear.num_bone_coeffs
    res.put("num_bone_coeffs", kb)
    iters = tuple(int(i) for i in args.iterations.split(","))
    fit = FitConfig(iterations=iters, lm_iterations=args.lm_iterations)  # type: ignore[arg-type]
    allregs = load_registration_set(args.regs, linear.num_vertices)
    allregs.vertices = allregs.vertices.to(dev)
    train = allregs.split("train")
    test = first_per_subject(allregs.split("test"), args.max_test)
    train_sub = first_per_subject(train, args.max_train)
    spiral_models = {lat: blsm.load(p).to(dev) for lat, p in spiral_paths.items()}
    ks_lin = [k for k in args.ks if k <= kb + args.shape_coeffs]
    ks_spiral = [kb + lat for lat in args.latents]
    curves: dict[str, dict] = {"test": {}, "train": {}}

    def curve(split: str, name: str, fittable, regs, ks: list[int]) -> None:  # noqa: ANN001
        t = time.time()
        cur = shape_curve(fittable, regs, EvalConfig(ks=tuple(ks), fit=fit, batch=args.batch))
        curves[split].setdefault(name, {}).update({str(k): asdict(s) for k, s in cur.items()})
        log(f"{split} {name}: " + ", ".join(f"k={k} {s.mean:.2f}" for k, s in cur.items()) + f" ({time.time() - t:.0f} s)")
        res.put("curves", curves)

    curve("test", "BLSM-linear", BLSMFittable(linear), test, ks_lin)
    for lat, model in spiral_models.items():
        curve("test", "BLSM-spiral", BLSMFittable(model), test, [kb + lat])
    smpl_curve(args, smpl_job, linear, res, curve, test, src)
    curve("train", "BLSM-linear", BLSMFittable(linear), train_sub, ks_spiral)  # the diagnostics
    for lat, model in spiral_models.items():
        curve("train", "BLSM-spiral", BLSMFittable(model), train_sub, [kb + lat])
    own = {}
    pos = {s: i for i, s in enumerate(rest_subjects)}
    idx = [pos[s] for s in train_sub.subjects]
    for lat, model in spiral_models.items():
        codes = model.population_shape[idx]
        errors, _ = fit_errors(BLSMFittable(model), train_sub.vertices.to(model.template.dtype), kb + lat, fit,
                               args.batch, fixed={"shape": codes})
        own[str(kb + lat)] = stats_dict(errors)
        log(f"train BLSM-spiral L={lat} at its own codes: {own[str(kb + lat)]['mean']:.2f} mm")
        res.put("own_code", own)
    res.put("seconds", round(time.time() - t0, 1))


def cmd_report(args: argparse.Namespace) -> None:
    from blsm.learn.evaluation.evaluate import line_plot

    d = json.loads((args.work / "fig4.json").read_text())
    kb = d["num_bone_coeffs"]
    test = d["curves"]["test"]
    ks = sorted({int(k) for c in test.values() for k in c})
    names = list(test)
    lines = ["| k | " + " | ".join(f"{n} (mm)" for n in names) + " |", "|---|" + "---:|" * len(names)]
    for k in ks:
        cells = [f"{test[n][str(k)]['mean']:.2f}" if str(k) in test[n] else "-" for n in names]
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    series = {n: ([float(k) for k in sorted(map(int, c))], [c[str(k)]["mean"] for k in sorted(map(int, c))])
              for n, c in test.items()}
    plot = args.out.with_suffix(".png")
    line_plot(series, plot, "Fig. 4 on our registrations (held-out subjects)", "number of coefficients k",
              "mean abs. vertex error (mm)")
    diag = ["| k (L) | spiral train fit | spiral held-out fit | spiral at own code (train) | linear train fit | "
            "linear held-out fit | AD residual error (train) | PCA residual error, L comps (train) |",
            "|---|---:|---:|---:|---:|---:|---:|---:|"]
    tr = d["curves"].get("train", {})
    for lat, s in d.get("spiral", {}).items():
        k = str(kb + int(lat))

        def g(c, k=k):  # noqa: ANN001, ANN202
            return f"{c[k]['mean']:.2f}" if c and k in c else "-"
        diag.append(f"| {k} ({lat}) | {g(tr.get('BLSM-spiral'))} | {g(test.get('BLSM-spiral'))} | "
                    f"{g(d.get('own_code'))} | {g(tr.get('BLSM-linear'))} | {g(test.get('BLSM-linear'))} | "
                    f"{s['train_error_mm']:.2f} | {s['pca_train_error_mm']:.2f} |")
    text = "\n".join(["## Fig. 4 on our registrations", "", *lines, "", f"![fig4](figures/{plot.name})", "",
                      "### Diagnostics (mm)", "", *diag, ""])
    args.out.with_suffix(".json").write_text(json.dumps(d, indent=1))
    print(text)


def cmd_codes(args: argparse.Namespace) -> None:
    """Optimisation diagnostic of the latent space alone: the decoders of a ``run`` (``--models``),
    the training residuals of a ``--learn-only`` run (``--learnt``). For the first ``--n`` training
    bodies: the error at the auto-decoder's own codes, and after a code search from z = 0 with the
    decoder fixed (:func:`blsm.spiral.autodecoder.fit_codes`). Adds ``code_search`` to the json."""
    from blsm.spiral.autodecoder import fit_codes, vertex_error_mm

    torch.set_num_threads(args.threads)
    resid = torch.load(args.learnt / "residuals.pt")["residuals"][: args.n].float()
    path = args.models / "fig4.json"
    d = json.loads(path.read_text())
    out = {}
    for lat in sorted(int(k) for k in d["spiral"]):
        model = blsm.load(args.models / f"blsm_spiral_{lat}.npz")
        dec = model.shape_decoder
        with torch.no_grad():
            own = vertex_error_mm(dec(model.population_shape[: args.n]), resid)
        t = time.time()
        _, err = fit_codes(dec, resid, steps=args.steps, lr=args.lr)
        out[str(lat)] = {"bodies": len(resid), "own_code_mm": float(own.mean()), "search_mm": float(err.mean()),
                         "steps": args.steps, "lr": args.lr, "seconds": round(time.time() - t, 1)}
        log(f"L={lat}: own codes {float(own.mean()):.3f} mm, code search from 0 {float(err.mean()):.3f} mm")
        d["code_search"] = out
        path.write_text(json.dumps(d, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("prepare")
    p.add_argument("--work", type=Path, required=True)
    p.add_argument("--model", default=None)
    p.add_argument("--regs", type=Path, default=None, help="registrations to copy without displacements")
    p.add_argument("--population", type=Path, default=None, help="population folder (index.json: the split)")
    p.set_defaults(func=cmd_prepare)
    r = sub.add_parser("run")
    r.add_argument("--regs", type=Path, required=True)
    r.add_argument("--work", type=Path, required=True)
    r.add_argument("--model", default=None, help="initial model (default: packaged, as blsm learn)")
    r.add_argument("--ops", type=Path, default=None, help="the hierarchy from prepare (default: WORK/ops.npz)")
    r.add_argument("--config", type=Path, default=Path("configs/blsm/train_default.yaml"))
    r.add_argument("--device", default="cpu")
    r.add_argument("--learn-device", default=None, help="device of blsm learn's steps (default: --device)")
    r.add_argument("--shape-coeffs", type=int, default=32)
    r.add_argument("--smpl-coeffs", type=int, default=32)
    r.add_argument("--latents", type=lambda s: [int(x) for x in s.split(",")], default=[2, 6, 14, 22])
    r.add_argument("--epochs", type=int, default=300)
    r.add_argument("--lr-decay", type=float, default=0.99)
    r.add_argument("--ks", type=lambda s: [int(x) for x in s.split(",")], default=[1, 2, 3, 4, 6, 8, 12, 16, 24, 32])
    r.add_argument("--iterations", default="100,100,100,300")
    r.add_argument("--lm-iterations", type=int, default=25)
    r.add_argument("--batch", type=int, default=32)
    r.add_argument("--max-test", type=int, default=0)
    r.add_argument("--max-train", type=int, default=30)
    r.add_argument("--learnt", type=Path, default=None, help="a WORK folder of an earlier --learn-only run")
    r.add_argument("--learn-only", action="store_true", help="stop after learning BLSM-linear")
    r.add_argument("--quick", action="store_true", help="few learning iterations (a smoke test)")
    r.set_defaults(func=cmd_run)
    o = sub.add_parser("report")
    o.add_argument("--work", type=Path, required=True)
    o.add_argument("--out", type=Path, required=True, help="path stem of the plot (.png) and the numbers (.json)")
    o.set_defaults(func=cmd_report)
    c = sub.add_parser("codes")
    c.add_argument("--models", type=Path, required=True, help="the WORK folder of a run")
    c.add_argument("--learnt", type=Path, required=True, help="the WORK folder of a --learn-only run")
    c.add_argument("--n", type=int, default=30)
    c.add_argument("--steps", type=int, default=300)
    c.add_argument("--lr", type=float, default=0.05)
    c.add_argument("--threads", type=int, default=1)
    c.set_defaults(func=cmd_codes)
    args = ap.parse_args()
    args.func(args)


if __name__ == "__main__":
    main()
