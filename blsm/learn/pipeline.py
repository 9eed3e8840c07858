"""``blsm train CONFIG --out MODEL``: scans to a learned BLSM in one command (thesis Sec. 5.4).

The run, each step resumable (what is on disk and matches is kept, never overwritten silently):

1. **Population** (:mod:`blsm.learn.scans.population`): the Anny stand-in scans (CAESAR-like rest scans of
   every subject, D-FAUST-like posed scans of some), with held-out subjects, in ``WORK/population``.
   A user's own scan folder in the same format can be named instead (``population.folder``).
2. **Registration** (:mod:`blsm.learn.registration.register`, Eqs. 5.13-5.25): every scan, in worker processes,
   one ``blsm-registration`` file per scan in ``WORK/registrations`` (existing files are kept, so an
   interrupted run continues where it stopped).
3. **Learning** (:mod:`blsm.learn.training.train`, Eqs. 5.26-5.31) on the training subjects' registrations:
   the model file ``MODEL`` (written atomically) and its report ``MODEL`` with ``.report.json``.

The config is one YAML file with the sections ``run``, ``population``, ``registration``, ``train``
and ``evaluation`` (``configs/blsm/train_default.yaml``; ``train_small.yaml`` is the one ``make
test`` runs). Unknown keys and wrong types are one-line errors naming the file and key path.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm import io
from blsm.config import config_from_dict
from blsm.learn.registration.register_config import RegisterConfig
from blsm.learn.training.train import TrainConfig


def _log(msg: str) -> None:
    print(f"[train] {msg}", file=sys.stderr, flush=True)


@dataclass(frozen=True)
class RunConfig:
    """Attributes:
    work: folder for the population and the registrations (relative to the current directory).
    workers: registration processes (0: one per core).
    batch: scans registered together in one process.
    rounds: registration + learning rounds; round r > 1 registers the scans again with the model
        learned in round r - 1 (its shape space initialises stage 1), as SMPL-type models are
        trained by alternating registration and model fitting.
    initial: ``"rig"`` starts from the initial model's (``--model``, default the packaged rig
        ``blsm/data/blsm_anny_rig.npz``) template, skeleton and blend weights only: any
        bone-corrective and shape blendshapes are removed, so nothing a model learnt from Anny's
        known correspondence reaches the registrations (the thesis' starting point, a rigged
        template). ``"model"`` uses the initial model as it is (its shape space then initialises
        stage 1).
    max_landmark_rms_mm: a registration whose landmark fit (Eq. 5.13, before the free-form stage)
        leaves a larger landmark RMS has failed (a pose the fit could not reach, e.g. a limb caught
        in a wrong local minimum); it is listed in the report and left out of the learning.
    """

    work: str = "out/train"
    workers: int = 0
    batch: int = 4
    rounds: int = 2
    initial: str = "rig"
    max_landmark_rms_mm: float = 40.0

    def __post_init__(self) -> None:
        if self.rounds < 1:
            raise ValueError(f"rounds must be >= 1, got {self.rounds}")
        if self.initial not in ("rig", "model"):
            raise ValueError(f"initial must be 'rig' or 'model', got {self.initial!r}")


@dataclass(frozen=True)
class PopulationConfig:
    """The scan population (:func:`blsm.learn.scans.population.make_population`).

    Attributes:
        folder: an existing population folder to use instead of making one ("" = make
            ``WORK/population``).
        subjects: people (each gets a rest-pose scan).
        posed_subjects: of them, people who also get posed scans; poses: posed scans each.
        seed, test_fraction: the draw and the share of held-out subjects.
        motions: a motion library folder for the poses ("" = the packaged pose prior).
    """

    folder: str = ""
    subjects: int = 1000
    posed_subjects: int = 60
    poses: int = 8
    seed: int = 0
    test_fraction: float = 0.1
    motions: str = ""


@dataclass(frozen=True)
class EvaluationConfig:
    """Held-out evaluation after learning (:mod:`blsm.learn.evaluation.evaluate`).

    Attributes:
        enabled: run it.
        coeffs: numbers of shape coefficients compared (Fig. 5.6).
        max_test: at most this many held-out registrations are fitted (0: all), chosen by
            :func:`blsm.learn.registration.registrations.spread_over_subjects`: all frames of ``sequences`` posed
            subjects, then round-robin over the other subjects.
        sequences: held-out subjects with posed scans whose every registration is kept (for pose
            generalisation).
        max_train_subjects: SMPL-reimpl is trained on the registrations of at most this many
            training subjects (its per-registration pose fits are the slow part; 0: all).
        iterations, lm_iterations: the staged fit (:class:`blsm.learn.evaluation.fit.FitConfig`).
        pose_generalisation: also fit shape on one frame and pose only on the others (Fig. 5.7).
        out: markdown report (plots and JSON beside it), relative to the current directory;
            "" = ``MODEL`` with ``_evaluation.md``.
    """

    enabled: bool = True
    coeffs: tuple[int, ...] = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32)
    max_test: int = 50
    sequences: int = 2
    max_train_subjects: int = 200
    iterations: tuple[int, ...] = (100, 100, 100, 300)
    lm_iterations: int = 25
    pose_generalisation: bool = True
    out: str = ""

    def __post_init__(self) -> None:
        if self.max_test < 0 or self.sequences < 0:
            raise ValueError(f"max_test and sequences must be >= 0, got {self.max_test} and {self.sequences}")
        if len(self.iterations) != 4:
            raise ValueError(f"iterations needs the Adam steps of the four stages, got {list(self.iterations)}")


@dataclass(frozen=True)
class PipelineConfig:
    run: RunConfig = field(default_factory=RunConfig)
    population: PopulationConfig = field(default_factory=PopulationConfig)
    registration: RegisterConfig = field(default_factory=RegisterConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)


def load_config(path: str | Path) -> PipelineConfig:
    """Read the whole run's YAML; unknown keys and wrong types are one-line errors."""
    data = io.read_yaml(path, "train config")
    return config_from_dict(PipelineConfig, data, str(path))


# ------------------------------------------------------------------------------------------------
# Steps


def population_step(cfg: PipelineConfig, work: Path, model_path: str) -> tuple[Path, dict]:
    """The population folder and its index: the configured one, or made (once) in WORK with the
    initial model's template and skeleton (the ground-truth correspondence is its template's)."""
    import blsm
    from blsm.learn.scans.population import make_population, read_population

    p = cfg.population
    if p.folder:
        folder = Path(p.folder)
        return folder, read_population(folder)
    folder = work / "population"
    want = {"subjects": p.subjects, "posed_subjects": p.posed_subjects, "poses": p.poses, "seed": p.seed,
            "test_fraction": p.test_fraction, "motions": p.motions, "rig_sha256": rig_sha256(model_path)}
    stamp = folder / "pipeline.json"
    if (folder / "index.json").is_file():
        had = json.loads(stamp.read_text()) if stamp.is_file() else None
        if had != want:
            raise ValueError(
                f"{folder}: holds a population made with other settings ({had}); "
                "remove it or set run.work to another folder"
            )
        _log(f"population: reusing {folder}")
        return folder, read_population(folder)
    t0 = time.time()
    index = make_population(
        folder, p.subjects, p.posed_subjects, p.poses, p.seed, p.test_fraction,
        motions=Path(p.motions) if p.motions else None, model=blsm.load(model_path),
    )  # fmt: skip
    with io.atomic_write(stamp, "w") as f:
        json.dump(want, f)
    _log(f"population: {sum(len(s['scans']) for s in index['subjects'])} scans in {time.time() - t0:.0f} s")
    return folder, index


def rig_sha256(model_path: str) -> str:
    """SHA-256 of what a population depends on in a model: template, skeleton, weights, DoF table."""
    import hashlib

    data = io.read_model(model_path)
    h = hashlib.sha256(data.dof_table_yaml.encode())
    for key in ("template", "faces", "heads", "frames", "weights"):
        h.update(np.ascontiguousarray(data.arrays[key]).tobytes())
    return h.hexdigest()


def scan_jobs(folder: Path, index: dict) -> list[tuple[Path, dict]]:
    """(scan file, meta to add: subject, split, pose number) for every scan of the population."""
    jobs = []
    for s in index["subjects"]:
        for k, rel in enumerate(s["scans"]):
            jobs.append((folder / rel, {"subject": s["id"], "split": s["split"], "pose": k}))
    return jobs


_WORKER: dict[str, Any] = {}


def _init_register_worker(model_path: str | None, reg_cfg: dict) -> None:
    import blsm
    from blsm.learn.registration.landmark_fit import default_selection

    torch.set_num_threads(1)
    model = blsm.load(model_path)
    _WORKER.update(model=model, cfg=RegisterConfig(**reg_cfg), selection=default_selection(model))


def _register_chunk(chunk: list[tuple[str, dict, str]]) -> list[str]:
    from blsm.learn.registration.register import register
    from blsm.learn.registration.registrations import save_registration
    from blsm.learn.scans.format import load_scan

    scans = []
    for path, extra, _ in chunk:
        scan = load_scan(path, require_landmarks=True)
        scan.meta = {**(scan.meta or {}), **extra, "id": Path(path).stem}
        scans.append(scan)
    regs = register(_WORKER["model"], scans, _WORKER["cfg"], selection=_WORKER["selection"], progress=False)
    for reg, (_, _, target) in zip(regs, chunk):
        save_registration(reg, target)
    return [target for _, _, target in chunk]


def registration_step(cfg: PipelineConfig, work: Path, jobs: list[tuple[Path, dict]], model_path: str) -> Path:
    """Register every scan without a registration file yet; return the registrations folder."""
    out = work / "registrations"
    out.mkdir(parents=True, exist_ok=True)
    # Registrations are kept across runs only when made with the same settings and model.
    want = {
        "registration": json.loads(json.dumps(asdict(cfg.registration))),
        "model_sha256": io.sha256_file(model_path),
    }
    stamp = out / "settings.json"
    if stamp.is_file():
        had = json.loads(stamp.read_text())
        if had != want:
            raise ValueError(
                f"{out}: holds registrations made with other settings or another model; "
                "remove them or set run.work to another folder"
            )
    else:
        with io.atomic_write(stamp, "w") as f:
            json.dump(want, f, indent=1)
    todo = [(str(p), extra, str(out / f"{p.stem}.npz")) for p, extra in jobs if not (out / f"{p.stem}.npz").is_file()]
    _log(f"registration: {len(jobs) - len(todo)} of {len(jobs)} scans already registered")
    if not todo:
        return out
    from blsm.learn.scans.format import load_scan

    for path, _, _ in todo:  # every scan is checked before any work: a bad one is a one-line error
        load_scan(path, require_landmarks=True)
    b = max(1, cfg.run.batch)
    chunks = [todo[i : i + b] for i in range(0, len(todo), b)]
    workers = cfg.run.workers or (os.cpu_count() or 1)
    workers = max(1, min(workers, len(chunks)))
    init = (model_path, asdict(cfg.registration))
    t0, done = time.time(), 0
    if workers == 1:
        _init_register_worker(*init)
        results = map(_register_chunk, chunks)
        pool = None
    else:
        pool = mp.get_context("spawn").Pool(workers, _init_register_worker, init)
        results = pool.imap_unordered(_register_chunk, chunks)
    try:
        last = 0.0
        for written in results:
            done += len(written)
            if time.time() - last > 30 or done == len(todo):
                last = time.time()
                rate = done / max(time.time() - t0, 1e-9)
                _log(f"registration: {done}/{len(todo)} scans, {rate * 60:.1f} scans/min, "
                     f"ETA {(len(todo) - done) / max(rate, 1e-9) / 60:.1f} min")
    finally:
        if pool is not None:
            pool.terminate()
            pool.join()
    return out


def learning_step(
    cfg: PipelineConfig, reg_folder: Path, out_model: Path, model_path: str | None, source: str,
    population: Path | None = None,
) -> dict:
    """Learn the model from the registrations (train split for the model; test kept for the report)."""
    import blsm
    from blsm.learn.registration.registrations import load_registrations
    from blsm.learn.training.train import learn_model

    regs = load_registrations([reg_folder])
    failed = [r for r in regs if _landmark_rms(r) > cfg.run.max_landmark_rms_mm]
    if failed:
        _log(f"learning: leaving out {len(failed)} failed registrations (landmark fit RMS above "
             f"{cfg.run.max_landmark_rms_mm} mm): {', '.join(str(r.meta.get('scan')) for r in failed)}")
    used = [r for r in regs if _landmark_rms(r) <= cfg.run.max_landmark_rms_mm]
    t0 = time.time()
    initial = blsm.load(model_path)
    data, report = learn_model(initial, used, cfg.train)
    report["failed_registrations"] = {str(r.meta.get("scan")): round(_landmark_rms(r), 1) for r in failed}
    data.meta["build_command"] = f"blsm train {source} --out {out_model}"
    io.save_model(data, out_model)
    # The learnt model keeps the initial one's topology and parts: no need to read it back.
    report["registration"] = registration_summary(
        regs, population, initial.faces.numpy(), initial.part_names, initial.vertex_parts.numpy()
    )
    report["learning_seconds"] = round(time.time() - t0, 1)
    return report


def _landmark_rms(reg: Any) -> float:
    """Landmark RMS (mm) of a registration's landmark fit, before the free-form stage."""
    m = reg.meta or {}
    return float(m.get("surface_fit_landmark_rms_mm", m.get("stage1_landmark_rms_mm", 0.0)))


def registration_summary(regs: list[Any], population: Path | None = None, faces: Any = None,
                         part_names: list[str] | None = None, vertex_parts: Any = None) -> dict:
    """Registration error against ground-truth correspondence (mm), by split, where scans had it.

    With the population folder and the model's ``faces``, each error vector is also split into its
    component along the true surface normal (off the surface) and the rest (sliding along the
    surface), and averaged per body part (``vertex_parts``, ``part_names``).
    """
    from blsm.mesh import vertex_normals

    out: dict[str, Any] = {}
    for split in ("train", "test"):
        rows = [r for r in regs if (r.meta or {}).get("split", "train") == split and "error_mean_mm" in r.meta]
        if not rows:
            continue
        means = np.array([r.meta["error_mean_mm"] for r in rows])
        entry = {
            "scans": len(rows),
            "error_mean_mm": float(means.mean()),
            "error_mean_mm_worst_scan": float(means.max()),
            "error_max_mm": float(max(r.meta["error_max_mm"] for r in rows)),
            "stage1_error_mean_mm": float(np.mean([r.meta["stage1_error_mean_mm"] for r in rows])),
            "rest_scans_error_mean_mm": float(np.mean([r.meta["error_mean_mm"] for r in rows if r.meta.get("pose") == 0] or [np.nan])),
            "posed_scans_error_mean_mm": float(np.mean([r.meta["error_mean_mm"] for r in rows if r.meta.get("pose") != 0] or [np.nan])),
        }
        if population is not None and faces is not None:
            normal, tangent, parts = [], [], []
            for r in rows:
                scan = population / "scans" / f"{r.meta['scan']}.npz"
                with np.load(scan, allow_pickle=False) as z:
                    gt = np.asarray(z["gt_points"], np.float64)
                d = np.asarray(r.vertices, np.float64) - gt
                n = vertex_normals(gt, faces)
                dn = (d * n).sum(1)
                normal.append(np.abs(dn).mean())
                tangent.append(np.linalg.norm(d - dn[:, None] * n, axis=1).mean())
                e = np.linalg.norm(d, axis=1)
                parts.append([e[vertex_parts == k].mean() for k in range(len(part_names or []))])
            entry["normal_mean_mm"] = float(np.mean(normal) * 1000)
            entry["tangential_mean_mm"] = float(np.mean(tangent) * 1000)
            if part_names:
                entry["by_part_mm"] = dict(zip(part_names, (np.mean(parts, 0) * 1000).round(2).tolist()))
        out[split] = entry
    return out


def evaluation_step(cfg: PipelineConfig, reg_folder: Path, population: Path, out_model: Path, work: Path) -> dict:
    """Train SMPL-reimpl on the same training registrations and compare it with the learned BLSM
    on the held-out ones (Sec. 5.5; :mod:`blsm.learn.evaluation.evaluate`)."""
    import blsm
    from blsm.learn.evaluation.evaluate import EvalConfig, evaluate, write_report
    from blsm.learn.evaluation.fit import BLSMFittable, FitConfig
    from blsm.learn.evaluation.smpl_reimpl import SMPLReimplFittable, SMPLTrainConfig, train_smpl_reimpl
    from blsm.learn.registration.registrations import load_registration_set, spread_over_subjects

    e = cfg.evaluation
    t0 = time.time()
    model = blsm.load(out_model)
    regs = load_registration_set(reg_folder, model.num_vertices, population)
    train, test = regs.split("train"), regs.split("test")
    if test.vertices.shape[0] == 0:
        raise ValueError(f"{population}: no held-out subject to evaluate on (raise population.test_fraction)")
    if e.max_train_subjects > 0:
        keep = sorted(set(train.subjects))[: e.max_train_subjects]
        train = train.select([i for i, s in enumerate(train.subjects) if s in keep])
    if e.max_test > 0 and test.vertices.shape[0] > e.max_test:
        test = test.select(spread_over_subjects(list(test.subjects), e.max_test, e.sequences))
    fit = FitConfig(iterations=e.iterations, lm_iterations=e.lm_iterations)  # type: ignore[arg-type]
    _log(f"evaluation: training SMPL-reimpl on {train.vertices.shape[0]} registrations of "
         f"{len(set(train.subjects))} subjects")
    smpl = train_smpl_reimpl(model, train.vertices, max(e.coeffs), train.subjects, SMPLTrainConfig(fit=fit))
    smpl.save(work / "smpl_reimpl.npz")
    _log(f"evaluation: fitting both models to {test.vertices.shape[0]} held-out registrations")
    rep = evaluate(
        {"BLSM-linear": BLSMFittable(model), "SMPL-reimpl": SMPLReimplFittable(smpl)},
        test,
        EvalConfig(ks=e.coeffs, fit=fit, pose_generalisation=e.pose_generalisation),
    )
    out = Path(e.out) if e.out else out_model.with_name(out_model.stem + "_evaluation.md")
    files = write_report(rep, out, title=f"BLSM-linear vs SMPL-reimpl ({model.meta.get('build_command', '')})")
    _log(f"evaluation: {', '.join(map(str, files))} ({time.time() - t0:.0f} s)")
    return {"files": [str(f) for f in files], "seconds": round(time.time() - t0, 1)}


def strip_to_rig(model_path: str | None, out: Path) -> Path:
    """Write the rig of the initial model (:func:`blsm.build_anny.rig_of`) to ``out``."""
    from blsm.build_anny import rig_of
    from blsm.model import DEFAULT_RIG

    io.save_model(rig_of(io.read_model(DEFAULT_RIG if model_path is None else model_path)), out)
    return out


def run(cfg: PipelineConfig, out_model: Path, model_path: str | None = None, source: str = "CONFIG") -> dict:
    """The whole pipeline (see the module docstring); returns the report (also written to disk)."""
    import dataclasses

    from blsm.model import DEFAULT_RIG

    t0 = time.time()
    work = Path(cfg.run.work)
    initial = str(DEFAULT_RIG) if model_path is None else model_path
    folder, index = population_step(cfg, work, initial)
    jobs = scan_jobs(folder, index)
    if not jobs:
        raise ValueError(f"{folder}: the population holds no scans")
    current = initial
    reg_cfg = cfg.registration
    if cfg.run.initial == "rig":
        current = str(strip_to_rig(initial, work / "initial_rig.npz"))
        # The rig has no shape space to initialise stage 1 with (round 1 is the thesis' Eq. 5.13).
        reg_cfg = dataclasses.replace(reg_cfg, shape_init=False)
    rounds: list[dict] = []
    for r in range(1, cfg.run.rounds + 1):
        _log(f"round {r} of {cfg.run.rounds}: registering with {current}")
        round_cfg = dataclasses.replace(cfg, registration=reg_cfg)
        reg_folder = registration_step(round_cfg, work / f"round{r}", jobs, current)
        target = out_model if r == cfg.run.rounds else work / f"round{r}" / "model.npz"
        rep = learning_step(cfg, reg_folder, target, current, source, folder)
        rounds.append({"round": r, "registration": rep["registration"], "errors_mm": rep.get("errors_mm")})
        current, reg_cfg = str(target), cfg.registration
    report = rep
    report["rounds"] = rounds
    if cfg.evaluation.enabled:
        report["evaluation"] = evaluation_step(cfg, reg_folder, folder, out_model, work)
    report["seconds_total"] = round(time.time() - t0, 1)
    report["config"] = json.loads(json.dumps(asdict(cfg)))
    report_path = out_model.with_suffix(".report.json")
    with io.atomic_write(report_path, "w") as f:
        json.dump(report, f, indent=1)
    _log(f"wrote {out_model} and {report_path} ({report['seconds_total'] / 60:.1f} min in all)")
    return report
