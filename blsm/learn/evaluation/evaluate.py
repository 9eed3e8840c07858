"""Held-out evaluation of BLSM-linear against SMPL-reimpl (thesis Sec. 5.5.2).

- Shape generalisation (Fig. 5.6, Table 5.2): every held-out registration is fitted with the staged
  fit (:mod:`blsm.learn.evaluation.fit`) for k free shape coefficients, k in a list; reported are the mean
  absolute vertex error (MABS, the mean Euclidean per-vertex distance) in mm, its standard
  deviation over all vertices of all registrations, and the area under the cumulative per-vertex
  error curve from 0 to ``auc_max`` mm (normalised to [0, 1]; 1 = every vertex exact).
- Pose generalisation (Fig. 5.7 right): the shape is fitted on one frame of each held-out subject
  (its first registration, the rest-pose one in a population folder), then only pose, global
  orientation and translation on its other frames, shape coefficients held fixed.
- Registration error: registered vertices against the ground-truth surface points of synthetic
  scans (``gt_points`` of the scan file), where they can be found.

Registrations are read from ``blsm-registration`` files (``vertices`` (V, 3) and a ``meta`` JSON
with the subject id, the pose id and the split); see
:func:`blsm.learn.registration.registrations.load_registration_set`. ``blsm evaluate`` is in :mod:`blsm.learn.cli`.

Writes a markdown section, a JSON file with every number, and PNG line plots (drawn with PIL: the
project's environment has no matplotlib).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from blsm.io import atomic_write
from blsm.learn.evaluation.fit import FitConfig, Fittable, staged_fit
from blsm.learn.registration.registrations import RegistrationSet

DEFAULT_KS = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32)
AUC_MAX_MM = 20.0


# --------------------------------------------------------------------------------------------
# Metrics


@dataclass
class ErrorStats:
    """Per-vertex error summary (mm).

    Attributes:
        mean: mean absolute vertex error (MABS).
        sd: standard deviation of the per-vertex errors.
        auc: area under the cumulative error distribution on [0, auc_max] mm, normalised to [0, 1].
        median, p95: percentiles.
        count: number of registrations.
    """

    mean: float
    sd: float
    auc: float
    median: float
    p95: float
    count: int


def error_stats(errors_m: torch.Tensor, auc_max_mm: float = AUC_MAX_MM) -> ErrorStats:
    """Summarise (N, V) per-vertex errors in metres."""
    e = errors_m.detach().double().flatten() * 1000.0
    if e.numel() == 0:
        raise ValueError("no errors to summarise")
    return ErrorStats(
        mean=float(e.mean()),
        sd=float(e.std()) if e.numel() > 1 else 0.0,
        auc=cumulative_auc(e, auc_max_mm),
        median=float(e.median()),
        p95=float(torch.quantile(e[: 10_000_000], 0.95)),
        count=int(errors_m.shape[0]),
    )


def cumulative_auc(errors_mm: torch.Tensor, max_mm: float = AUC_MAX_MM) -> float:
    """Area under ``F(t) = P(error <= t)`` for t in [0, max_mm], divided by max_mm.

    Equals ``mean(max(0, 1 - min(e, max) / max))``; 1 means every error is 0.
    """
    e = errors_mm.double().clamp(max=max_mm)
    return float((1.0 - e / max_mm).mean())


# --------------------------------------------------------------------------------------------
# Experiments


@dataclass
class EvalConfig:
    """Settings of :func:`evaluate`.

    Attributes:
        ks: numbers of shape coefficients (Fig. 5.6's x axis); values above a model's total are
            skipped for that model.
        fit: staged-fit settings.
        batch: registrations fitted together.
        auc_max_mm: upper end of the cumulative error curve.
        pose_generalisation: whether to run the Fig. 5.7 (right) experiment.
    """

    ks: tuple[int, ...] = DEFAULT_KS
    fit: FitConfig = field(default_factory=lambda: FitConfig(lm_iterations=25))
    batch: int = 16
    auc_max_mm: float = AUC_MAX_MM
    pose_generalisation: bool = True


def fit_errors(
    fittable: Fittable,
    targets: torch.Tensor,
    num_coeffs: int,
    fit: FitConfig,
    batch: int,
    fixed: dict[str, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Staged fit in batches; returns (N, V) errors in metres and the fitted coefficient groups."""
    errs, coeffs = [], {k: [] for k in fittable.coeff_sizes}
    for i in range(0, targets.shape[0], batch):
        sl = slice(i, i + batch)
        fx = None if fixed is None else {k: v[sl] for k, v in fixed.items()}
        res = staged_fit(fittable, targets[sl], num_coeffs=num_coeffs, config=fit, fixed_coeffs=fx)
        errs.append(res.errors)
        for k in coeffs:
            coeffs[k].append(res.params[k])
    return torch.cat(errs), {k: torch.cat(v) for k, v in coeffs.items()}


def shape_curve(
    fittable: Fittable, regs: RegistrationSet, cfg: EvalConfig
) -> dict[int, ErrorStats]:
    """Fig. 5.6 / Table 5.2: error statistics per number of coefficients k."""
    dtype = fittable.skeleton.template.dtype
    targets = regs.vertices.to(dtype)
    out = {}
    for k in cfg.ks:
        if k > fittable.num_coeffs_max:
            continue
        errors, _ = fit_errors(fittable, targets, k, cfg.fit, cfg.batch)
        out[k] = error_stats(errors, cfg.auc_max_mm)
    return out


def pose_curve(
    fittable: Fittable, regs: RegistrationSet, cfg: EvalConfig
) -> dict[int, ErrorStats]:
    """Fig. 5.7 right: shape from each subject's first frame, then pose only on the other frames."""
    dtype = fittable.skeleton.template.dtype
    first: dict[str, int] = {}
    for i, s in enumerate(regs.subjects):
        first.setdefault(s, i)
    others = [i for i, s in enumerate(regs.subjects) if first[s] != i]
    if not others:
        return {}
    subj = sorted(first)
    shape_idx = [first[s] for s in subj]
    out = {}
    for k in cfg.ks:
        if k > fittable.num_coeffs_max:
            continue
        _, coeffs = fit_errors(fittable, regs.vertices[shape_idx].to(dtype), k, cfg.fit, cfg.batch)
        row = torch.tensor([subj.index(regs.subjects[i]) for i in others])
        fixed = {g: c[row] for g, c in coeffs.items()}
        errors, _ = fit_errors(fittable, regs.vertices[others].to(dtype), k, cfg.fit, cfg.batch, fixed)
        out[k] = error_stats(errors, cfg.auc_max_mm)
    return out


def registration_errors(regs: RegistrationSet, auc_max_mm: float = AUC_MAX_MM) -> ErrorStats | None:
    """Registered vertices against ground-truth correspondences, where known."""
    idx = [i for i, g in enumerate(regs.gt_points) if g is not None]
    if not idx:
        return None
    gt = torch.from_numpy(np.stack([regs.gt_points[i] for i in idx]))
    return error_stats((regs.vertices[idx] - gt).norm(dim=-1), auc_max_mm)


@dataclass
class EvalReport:
    """All numbers of one evaluation (mm); ``shape[model][k]`` and ``pose[model][k]``."""

    shape: dict[str, dict[int, ErrorStats]]
    pose: dict[str, dict[int, ErrorStats]]
    registration: ErrorStats | None
    info: dict


def evaluate(
    models: dict[str, Fittable], regs: RegistrationSet, cfg: EvalConfig | None = None, targets: str = "registrations"
) -> EvalReport:
    """Run the shape (and pose) generalisation experiments on ``regs`` for every model.

    ``targets="ground-truth"`` fits the true bodies of the registrations instead
    (:meth:`RegistrationSet.ground_truth`).
    """
    cfg = cfg or EvalConfig()
    if targets not in ("registrations", "ground-truth"):
        raise ValueError(f"targets must be 'registrations' or 'ground-truth', got {targets!r}")
    reg_error = registration_errors(regs, cfg.auc_max_mm)
    if targets == "ground-truth":
        regs = regs.ground_truth()
    if regs.vertices.shape[0] == 0:
        raise ValueError("no registrations to evaluate")
    t0 = time.time()
    shape = {name: shape_curve(f, regs, cfg) for name, f in models.items()}
    pose = {name: pose_curve(f, regs, cfg) for name, f in models.items()} if cfg.pose_generalisation else {}
    info = {
        "registrations": int(regs.vertices.shape[0]),
        "subjects": len(set(regs.subjects)),
        "fit": asdict(cfg.fit),
        "seconds": round(time.time() - t0, 1),
        "max_coeffs": {name: f.num_coeffs_max for name, f in models.items()},
        "targets": targets,
    }
    return EvalReport(shape, pose, reg_error, info)


# --------------------------------------------------------------------------------------------
# Output: markdown, JSON, PNG


def _table(curves: dict[str, dict[int, ErrorStats]], ks: list[int]) -> list[str]:
    names = list(curves)
    head = "| k | " + " | ".join(f"{n} error (mm) | {n} AUC" for n in names) + " |"
    rule = "|---|" + "---|---|" * len(names)
    lines = [head, rule]
    for k in ks:
        cells = []
        for n in names:
            s = curves[n].get(k)
            cells += ["-", "-"] if s is None else [f"{s.mean:.2f} ± {s.sd:.2f}", f"{s.auc:.3f}"]
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    return lines


def write_report(report: EvalReport, out: str | Path, title: str = "BLSM evaluation") -> list[Path]:
    """Write ``out`` (markdown), and beside it in ``figures/`` ``<stem>.json`` and ``<stem>_shape.png`` /
    ``<stem>_pose.png`` (generated files apart from the written documents, as in ``docs/figures``)."""
    out = Path(out)
    stem = out.with_suffix("")
    figures = out.parent / "figures"
    figures.mkdir(parents=True, exist_ok=True)
    written = []
    ks = sorted({k for c in report.shape.values() for k in c})
    lines = [f"## {title}", ""]
    what = ("the true bodies (ground-truth correspondence) of "
            if report.info.get("targets") == "ground-truth" else "")
    lines.append(
        f"Models fitted to {what}{report.info['registrations']} held-out registrations of "
        f"{report.info['subjects']} subjects; "
        f"staged fit (Sec. 5.5.2): Adam lr {report.info['fit']['lr']}, "
        f"x{report.info['fit']['plateau_factor']} "
        f"on plateau, {tuple(report.info['fit']['iterations'])} steps per stage, "
        f"then {report.info['fit']['lm_iterations']} Levenberg-Marquardt steps (not in the thesis). "
        f"Errors are per-vertex Euclidean distances (mean ± sd over all vertices); AUC is the area under "
        f"the cumulative per-vertex error distribution on [0, {AUC_MAX_MM:g}] mm, normalised."
    )
    lines += ["", "### Shape generalisation (Fig. 5.6, Table 5.2)", ""]
    lines += _table(report.shape, ks)
    plot = figures / f"{stem.name}_shape.png"
    line_plot(
        {n: ([float(k) for k in c], [c[k].mean for k in c]) for n, c in report.shape.items()},
        plot, "Shape generalisation", "number of shape coefficients", "mean abs. vertex error (mm)",
    )
    written.append(plot)
    lines += ["", f"![shape generalisation](figures/{plot.name})"]
    if any(report.pose.values()):
        pks = sorted({k for c in report.pose.values() for k in c})
        lines += ["", "### Pose generalisation (Fig. 5.7 right)", "",
                  "Shape fitted on each subject's first registration, pose only on the others.", ""]
        lines += _table(report.pose, pks)
        plot = figures / f"{stem.name}_pose.png"
        line_plot(
            {n: ([float(k) for k in c], [c[k].mean for k in c]) for n, c in report.pose.items()},
            plot, "Pose generalisation", "number of shape coefficients", "mean abs. vertex error (mm)",
        )
        written.append(plot)
        lines += ["", f"![pose generalisation](figures/{plot.name})"]
    if report.registration is not None:
        r = report.registration
        lines += ["", "### Registration error against ground-truth correspondences", "",
                  f"{r.count} registrations: {r.mean:.2f} ± {r.sd:.2f} mm (median {r.median:.2f}, "
                  f"95th percentile {r.p95:.2f}), AUC {r.auc:.3f}."]
    lines += ["", _verdict(report), ""]
    with atomic_write(out, "w") as fh:
        fh.write("\n".join(lines))
    written.insert(0, out)
    js = figures / f"{stem.name}.json"
    payload = {
        "shape": {n: {str(k): asdict(s) for k, s in c.items()} for n, c in report.shape.items()},
        "pose": {n: {str(k): asdict(s) for k, s in c.items()} for n, c in report.pose.items()},
        "registration": None if report.registration is None else asdict(report.registration),
        "info": report.info,
    }
    with atomic_write(js, "w") as fh:
        json.dump(payload, fh, indent=1)
    written.append(js)
    return written


def _verdict(report: EvalReport) -> str:
    if "BLSM-linear" not in report.shape or "SMPL-reimpl" not in report.shape:
        return ""
    a, b = report.shape["BLSM-linear"], report.shape["SMPL-reimpl"]
    common = [k for k in a if k in b]
    worse = [k for k in common if a[k].mean >= b[k].mean]
    if not worse:
        return f"BLSM-linear has the lower shape error for every k in {common}."
    return f"BLSM-linear is **not** better than SMPL-reimpl for k in {worse} (shape generalisation)."


# A small line plotter on PIL (axes, ticks, legend).
_COLOURS = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14)]


def _nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    if hi <= lo:
        hi = lo + 1.0
    raw = (hi - lo) / n
    mag = 10 ** math.floor(math.log10(raw))
    step = min((m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw), default=10 * mag)
    start = math.floor(lo / step) * step
    ticks = [round(start, 10)]
    while ticks[-1] < hi - 1e-9 * step:  # the last tick is at or above hi, so every point fits
        ticks.append(round(ticks[-1] + step, 10))
    return ticks


def line_plot(
    series: dict[str, tuple[list[float], list[float]]],
    path: str | Path,
    title: str,
    xlabel: str,
    ylabel: str,
    size: tuple[int, int] = (720, 480),
) -> Path:
    """Draw lines with markers, axes, ticks, labels and a legend to a PNG with PIL."""
    from PIL import Image, ImageDraw, ImageFont

    w, h = size
    left, right, top, bottom = 80, 20, 40, 60
    img = Image.new("RGB", size, "white")
    d = ImageDraw.Draw(img)
    font = ImageFont.load_default()
    xs = [x for xv, _ in series.values() for x in xv]
    ys = [y for _, yv in series.values() for y in yv]
    if not xs:
        xs, ys = [0.0, 1.0], [0.0, 1.0]
    xt = _nice_ticks(min(xs), max(xs))
    yt = _nice_ticks(0.0, max(ys) * 1.05)
    x0, x1, y0, y1 = xt[0], xt[-1], yt[0], yt[-1]

    def px(x: float, y: float) -> tuple[float, float]:
        return (
            left + (x - x0) / (x1 - x0) * (w - left - right),
            h - bottom - (y - y0) / (y1 - y0) * (h - top - bottom),
        )

    d.rectangle([left, top, w - right, h - bottom], outline="black")
    for t in xt:
        x, _ = px(t, y0)
        d.line([x, h - bottom, x, h - bottom + 5], fill="black")
        d.line([x, top, x, h - bottom], fill=(230, 230, 230))
        label = f"{t:g}"
        d.text((x - 3 * len(label), h - bottom + 8), label, fill="black", font=font)
    for t in yt:
        _, y = px(x0, t)
        d.line([left - 5, y, left, y], fill="black")
        d.line([left, y, w - right, y], fill=(230, 230, 230))
        label = f"{t:g}"
        d.text((left - 8 - 6 * len(label), y - 6), label, fill="black", font=font)
    d.rectangle([left, top, w - right, h - bottom], outline="black")
    d.text((w // 2 - 3 * len(title), 12), title, fill="black", font=font)
    d.text((w // 2 - 3 * len(xlabel), h - 25), xlabel, fill="black", font=font)
    ylab = Image.new("RGB", (6 * len(ylabel) + 4, 14), "white")
    ImageDraw.Draw(ylab).text((2, 0), ylabel, fill="black", font=font)
    ylab = ylab.rotate(90, expand=True)
    img.paste(ylab, (8, top + (h - top - bottom - ylab.size[1]) // 2))
    for i, (name, (xv, yv)) in enumerate(series.items()):
        c = _COLOURS[i % len(_COLOURS)]
        pts = [px(x, y) for x, y in zip(xv, yv)]
        if len(pts) > 1:
            d.line(pts, fill=c, width=2)
        for x, y in pts:
            d.ellipse([x - 3, y - 3, x + 3, y + 3], fill=c)
        ly = top + 10 + 16 * i
        d.line([w - right - 150, ly + 6, w - right - 125, ly + 6], fill=c, width=2)
        d.text((w - right - 118, ly), name, fill="black", font=font)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as fh:
        img.save(fh, format="PNG")
    return path
