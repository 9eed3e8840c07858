"""The run: ``synth generate``'s checks, lock, subjects and shards, on either engine.

``generate(config, out, ...)`` makes ``out/subjects/`` (the people, once per dataset, from the seed)
and then the shards. A sample's randomness is ``sample_rng(seed, index)`` only, so any worker can
make any sample, and a resumed run makes the same dataset as an uninterrupted one. The samples are
made by workers (:mod:`synth.worker`: a process pool here, or Ray tasks, :mod:`synth.engine_ray`),
each of which loads the model, subjects and backgrounds once and keeps one Mitsuba scene per mesh
topology, updated in place per image (:mod:`synth.sample`); a worker is replaced after
``render.recycle_after`` images.

Before any work, every input file is opened and checked (:func:`check_inputs`) and the output
folder is locked for this writer (:mod:`synth.lock`); bad input leaves no new file or folder, and a
failed write (a full disk) keeps the finished shards for ``--resume``. A run stops early only
where the shards it makes are chosen (``stop_after``, :meth:`synth.dataset.shards.ShardWriter.pending`).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import multiprocessing as mp
import os
import shutil
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm import mitsuba_util
from blsm.io import atomic_write, sha256_file
from synth import lock as out_lock
from synth import worker
from synth.backgrounds import background_kind
from synth.config import GeneratorConfig
from synth.dataset.shards import ShardWriter, SkipSample, WriteError
from synth.people import subject_pool_warning
from synth.poses import PoseSource
from synth.progress import Progress, log
from synth.sample import SUBJECTS
from synth.subjects import anny_subject, load_subject, model_fingerprint, save_subject

SUBJECTS_LOCK = ".lock-subjects"
ENGINES = ("local", "ray")
Plan = tuple[list[int], dict[str, Any], list[dict[str, Any]]]
"""What :meth:`synth.dataset.shards.ShardWriter.pending` returns: the shards to make, the finished ones'
manifest entries, and the samples skipped in those."""


def versions() -> dict[str, str]:
    """The package versions a manifest records (Python, numpy, torch, Mitsuba, Dr.Jit, blsm)."""
    import drjit
    import mitsuba

    import blsm

    out = {"python": sys.version.split()[0], "numpy": np.__version__, "torch": torch.__version__}
    out["mitsuba"], out["drjit"] = mitsuba.__version__, drjit.__version__
    out["blsm"] = getattr(blsm, "__version__", "0.1.0")
    return out


def choose_variant(cfg: GeneratorConfig) -> str:
    """The Mitsuba variant, once per run: the configured one, else cuda where a GPU is, else llvm."""
    if cfg.render.variant:
        return mitsuba_util.choose_variant((cfg.render.variant,))
    cands = ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb") if shutil.which("nvidia-smi") else ("llvm_ad_rgb", "scalar_rgb")
    return mitsuba_util.choose_variant(cands)


# ------------------------------------------------------------------------------------------------
# Subjects


def subject_rng(seed: int, i: int) -> np.random.Generator:
    # A three-word seed sequence: never equal to a sample's (seed, index).
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), 1, int(i)])))


def prepare_subjects(cfg: GeneratorConfig, out: Path, model: Any) -> list[Path]:
    """Make (or reuse) ``out/subjects/*.npz`` and ``subjects/index.json``; return the files."""
    folder = out / SUBJECTS
    folder.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    skipped: list[dict[str, str]] = []
    if cfg.subjects.source == "anny":
        # A subject depends on the model (its registration), the seed and the texture size: one
        # made with other ones must not be reused, or a resumed run would not be the same dataset.
        stamp = {"model": model_fingerprint(model), "seed": cfg.seed, "texture_size": cfg.subjects.texture_size,
                 "population": json.loads(json.dumps(asdict(cfg.subjects.population())))}  # as stored (lists)
        if cfg.subjects.detail:  # stamped only when on, so folders made before the key stay valid
            stamp["detail"] = True
        n = cfg.subjects.count
        paths = [folder / f"anny_{i:04d}.npz" for i in range(n)]
        for path in paths:  # every subject already made is checked before any is made
            if path.exists():  # written atomically, so complete: a damaged one is an error
                had = load_subject(path).meta.get("made_with")
                if had != stamp:
                    keys = [*stamp, *(k for k in had or {} if k not in stamp)]
                    what = "an earlier version" if had is None else ", ".join(
                        k for k in keys if had.get(k) != stamp.get(k)) + " differs"
                    raise ValueError(f"{path}: subject made with other settings ({what}); "
                                     "remove the dataset's subjects folder or use another --out")
        todo = [i for i, path in enumerate(paths) if not path.exists()]
        if todo:  # the slow step before the first image: said before it starts
            log(f"making {len(todo)} of {n} subjects in {folder} (Anny bodies registered to BLSM and textured, "
                "15-50 s each; about 80 s more once per machine while Anny compiles its kernels)")
        for i in todo:
            t0 = time.time()
            s = anny_subject(model, paths[i].stem, subject_rng(cfg.seed, i), cfg.subjects.texture_size,
                             cfg.subjects.population(), detail=cfg.subjects.detail, detail_seed=cfg.seed)
            s.meta["made_with"] = stamp
            save_subject(s, paths[i])
            log(f"subject {i + 1}/{n} {paths[i].stem}: height {s.meta['height_m']:.2f} m, "
                f"fit {s.meta['registration']['fit_mean_mm']:.1f} mm ({time.time() - t0:.0f} s)")
    else:
        from synth.scans import import_scans

        subjects, skipped_pairs = import_scans(model, Path(cfg.subjects.folder), skip_bad=cfg.skip_bad)
        skipped = [{"subject": n, "reason": r} for n, r in skipped_pairs]
        for s in subjects:
            paths.append(save_subject(s, folder / f"{s.id}.npz"))
        if not paths:
            raise ValueError(f"{cfg.subjects.folder}: no usable scan")
    index = {"subjects": {p.stem: sha256_file(p) for p in paths}, "skipped": skipped}
    with atomic_write(folder / "index.json", "w", f"{os.getpid()}") as fh:
        fh.write(json.dumps(index, indent=1, sort_keys=True) + "\n")
    return paths


# ------------------------------------------------------------------------------------------------
# The run


def run_writer(cfg: GeneratorConfig, out: Path, part: tuple[int, int] = (1, 1)) -> ShardWriter:
    """The shard writer of a run: ``num`` images, or ``num`` sequences of ``sequence.frames`` frames
    with ``sequence.per_shard`` whole sequences a shard (docs/video.md, Storage)."""
    n = worker.frames_per_sample(cfg)
    size = cfg.sequence.per_shard * n if cfg.sequence.enabled else cfg.output.shard_size
    return ShardWriter(out, cfg.num * n, size, cfg.seed, config=cfg_json(cfg), versions=versions(), part=part)


def generate(
    cfg: GeneratorConfig,
    out: str | Path,
    workers: int = 1,
    resume: bool = False,
    progress: bool = True,
    stop_after: int | None = None,
    on_image: Callable[[int], None] | None = None,
    part: tuple[int, int] = (1, 1),
    engine: str = "local",
    address: str | None = None,
    replace_stale: bool = False,
) -> dict[str, Any]:
    """Generate the dataset of ``cfg`` into ``out``; return the manifest.

    Worker processes make samples (any sample, from ``(seed, index)`` alone); this process writes
    them into shards in index order with :meth:`synth.dataset.shards.ShardWriter.run` (each shard to a
    temporary file renamed when complete, the manifest rewritten after every shard). Workers are replaced after ``render.recycle_after``
    images, which bounds any memory a long run might accumulate in them.

    Args:
        cfg: the configuration (``cfg.num`` samples).
        out: the dataset folder.
        workers: worker processes; 1 makes the samples in this process.
        resume: continue an interrupted run (keeps shards whose checksum matches).
        progress: report progress with rate and ETA on stderr.
        stop_after: stop after this many shards (tests).
        on_image: called in this process as ``on_image(images_done)`` after each image
            (benchmarks).
        part: ``(I, N)``: make only part ``I`` of ``N`` (:mod:`synth.dataset.shards`, Parts): its shards
            and ``manifest-part-I-of-N.json``; ``synth merge`` joins the parts.
        engine: ``"local"`` (a process pool of ``workers``) or ``"ray"`` (one Ray task per shard,
            :mod:`synth.engine_ray`; ``workers`` is not used).
        address: the Ray cluster to join (``engine="ray"``); None starts a local one.
        replace_stale: with ``resume``, a dataset in ``out`` made by another run (config, seed,
            count or shard size) is moved to a sibling folder by :func:`set_aside_stale` instead
            of refusing the run (``make demo`` after the defaults changed).

    Every input file (backgrounds, scans, poses) is opened and checked first; then the folder is
    locked (:mod:`synth.lock`: one writer per folder; temporary files carry the writer's tag). Bad
    input leaves no new file or folder behind.

    Raises:
        ValueError: bad input (config, subjects, backgrounds, poses), before any shard is written;
            the folder held by another run; a failed write (:class:`synth.dataset.shards.WriteError`, e.g.
            a full disk), with the finished shards kept for ``--resume``.
        RuntimeError: a sample failed (without ``cfg.skip_bad``); finished shards are kept.
    """
    import blsm

    if engine not in ENGINES:
        raise ValueError(f"unknown engine {engine!r}; choose one of {list(ENGINES)}")
    out = Path(out)
    writer = run_writer(cfg, out, part)
    if not writer.shards():
        raise ValueError(f"part {part[0]}/{part[1]} has no shards: the dataset has {writer.num_shards}")
    if not (resume and replace_stale):
        writer.pending(resume)  # fail fast (a dataset already there); checked again under the lock
    elif part != (1, 1):
        raise ValueError("replace_stale (--replace-stale) sets aside a whole dataset; it cannot be used with --part")
    model = blsm.load()
    check_inputs(cfg, model)
    if resume and replace_stale:
        aside = set_aside_stale(writer)
        if aside is not None:
            log(f"{out}: held a dataset made with other settings; moved it to {aside}")
    variant = choose_variant(cfg)
    # The cluster is reached (or Ray found missing) before anything is made.
    with _ray_session(address) if engine == "ray" else contextlib.nullcontext():
        return _generate(cfg, out, writer, model, variant, workers, resume, progress, stop_after, on_image, part,
                         engine)


def set_aside_stale(writer: ShardWriter) -> Path | None:
    """Move what ``writer``'s folder holds to ``<folder>.stale-<UTC time>`` when its manifest
    describes another run (:meth:`synth.dataset.shards.ShardWriter.same_run`); return that folder, or None
    when there was nothing to move (no manifest, or the same run, which ``--resume`` continues).

    Nothing is deleted. The folder is locked for the move (:mod:`synth.lock`), so a run writing
    into it is never moved from under it; every entry but the lock files moves, and the folder stays
    (empty) for the new run. An unreadable manifest is not a run to set aside: it stays an error.
    """
    out = writer.out
    if not writer.manifest_path.exists():
        return None
    with out_lock.acquire(out, 1, 1, warn=log):
        man = writer.read_manifest()
        if man is None:  # removed before the lock was taken
            return None
        try:
            writer.same_run(man, writer.manifest_path)
        except ValueError:  # another run's dataset (or not one of ours): moved, not refused
            pass
        else:
            return None
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        aside = out.with_name(f"{out.name}.stale-{stamp}")
        n = 1
        while aside.exists():
            n += 1
            aside = out.with_name(f"{out.name}.stale-{stamp}-{n}")
        aside.mkdir()
        for entry in sorted(out.iterdir()):
            if not entry.name.startswith(out_lock.LOCK_PREFIX):
                entry.rename(aside / entry.name)
    return aside


@contextlib.contextmanager
def _ray_session(address: str | None) -> Iterator[None]:
    """Connected to the Ray cluster at ``address`` (:func:`synth.engine_ray.connect`) for the block;
    disconnected after it unless this process was connected before."""
    from synth.engine_ray import connect

    started = connect(address)
    try:
        yield
    finally:
        if started:
            import ray

            ray.shutdown()


def _generate(
    cfg: GeneratorConfig,
    out: Path,
    writer: ShardWriter,
    model: Any,
    variant: str,
    workers: int,
    resume: bool,
    progress: bool,
    stop_after: int | None,
    on_image: Callable[[int], None] | None,
    part: tuple[int, int],
    engine: str,
) -> dict[str, Any]:
    """:func:`generate` once its inputs are checked: lock, subjects, shards."""
    created = _first_missing(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        lock = out_lock.acquire(out, *part, warn=log, stale_files=writer.temporary_files)
    except OSError as exc:
        _remove(created)
        raise WriteError.of(Path(exc.filename or out), exc) from None
    except BaseException:
        _remove(created)
        raise
    with lock:
        writer.tag = lock.tag
        new_subjects = not (out / SUBJECTS).exists()
        try:
            plan = writer.pending(resume, stop_after)
            if part[1] > 1:  # parts running side by side make the subjects once
                with out_lock.exclusive(out / SUBJECTS_LOCK, lambda: log("waiting for another part to make the subjects")):
                    prepare_subjects(cfg, out, model)
            else:
                prepare_subjects(cfg, out, model)
        except (ValueError, OSError) as exc:
            # Bad input found before any shard: leave the folder as it was.
            lock.release()
            _remove(created if created is not None else out / SUBJECTS if new_subjects else None)
            if isinstance(exc, OSError):
                raise WriteError.of(Path(exc.filename or out / SUBJECTS), exc) from None
            raise
        meter = Progress(sum(len(writer.indices(s)) for s in plan[0]), progress)
        if engine == "ray":
            from synth.engine_ray import run_ray

            man = run_ray(cfg, writer.config, out, writer, plan, variant, meter, on_image)
        else:
            man = _run(cfg, out, writer, plan, variant, workers, meter, on_image)
        meter.done(man)
        return man


def merge(out: str | Path) -> dict[str, Any]:
    """``synth merge DIR``: join the parts of a partitioned run (:func:`synth.dataset.shards.merge_parts`)
    under the folder's lock (refused while a part still runs); return the manifest."""
    from synth.dataset.shards import merge_parts

    out = Path(out)
    if not out.is_dir():
        raise ValueError(f"{out}: no such dataset folder")
    with out_lock.acquire(out, warn=log) as lock:
        man = merge_parts(out, lock.tag)
        (out / SUBJECTS_LOCK).unlink(missing_ok=True)
    return man


def check_inputs(cfg: GeneratorConfig, model: Any) -> None:
    """Open and check every input file of a run before any work: the pose source (for sequences, clips
    long enough), every background file (decoded as the workers will) and every scan folder; a
    ValueError names the first bad one. Then the subject pool against ``people.max``
    (:func:`synth.people.subject_pool_warning`): one line when it is smaller, an error when
    ``people.distinct`` is true."""
    poses = PoseSource(cfg)
    if cfg.sequence.enabled:
        from synth.sequence import eligible_clips

        eligible_clips(cfg, poses.clips, model.dof_limits.numpy())
    background_kind(cfg.background.kind).check(cfg.background)
    pool = cfg.subjects.count
    if cfg.subjects.source == "folder":
        from synth.scans import check_scans, subject_folders

        scans = Path(cfg.subjects.folder)
        pool = len(subject_folders(scans)) - len(check_scans(model, scans, skip_bad=cfg.skip_bad))
    warning = subject_pool_warning(cfg, pool)  # once a run, before any work; an error with people.distinct
    if warning:
        log(warning)


def _first_missing(path: Path) -> Path | None:
    """The outermost folder of ``path`` that does not exist yet (what ``mkdir -p`` would make)."""
    missing = None
    for p in (path, *path.parents):
        if p.exists():
            break
        missing = p
    return missing


def _remove(path: Path | None) -> None:
    if path is not None and path.exists():
        shutil.rmtree(path, ignore_errors=True)


def _run(
    cfg: GeneratorConfig,
    out: Path,
    writer: ShardWriter,
    plan: Plan,
    variant: str,
    workers: int,
    meter: Progress,
    on_image: Callable[[int], None] | None,
) -> dict[str, Any]:
    """The shards of ``plan`` made by a process pool of ``workers`` (:mod:`synth.worker`; one makes
    them in this process), once the inputs are checked and the lock is held."""
    todo, done, _ = plan
    indices = [i for s in todo for i in writer.indices(s)]
    workers = max(1, min(workers, -(-len(indices) // worker.frames_per_sample(cfg))))
    plural = "s" * (workers > 1)
    log(f"{len(indices)} images in {len(todo)} shards -> {out} ({workers} worker{plural}, Mitsuba {variant})")
    results, pool = _results(cfg, writer.config, out, indices, variant, workers)

    def make_sample(i: int, rng: np.random.Generator) -> dict[str, bytes]:
        # The samples come from the workers, in index order; each worker drew this same rng itself.
        index, fields, kind, msg = next(results)
        if index != i:
            raise RuntimeError(f"sample {i}: a worker returned sample {index} in its place")
        meter.tick()
        if on_image is not None:
            on_image(meter.made)
        if fields is not None:
            return fields
        if cfg.skip_bad:
            raise SkipSample(f"{kind}: {msg}")
        raise RuntimeError(f"sample {i}: {msg}")

    shards_done = len(done)

    def on_shard(s: int, count: int) -> None:
        nonlocal shards_done
        shards_done += 1
        meter.shard(writer.progress_line(s, count, shards_done))

    # In this process (one worker), numpy's BLAS keeps one thread while samples are made: its idle
    # threads would otherwise spin on the cores Dr.Jit renders with (see synth.worker.init_worker).
    from threadpoolctl import threadpool_limits

    try:
        with threadpool_limits(limits=1) if pool is None else contextlib.nullcontext():
            man = writer.run(make_sample, on_shard=on_shard, plan=plan)
    finally:
        if pool is not None:
            pool.terminate()
            pool.join()
    meter.close()
    return man


def _results(cfg: GeneratorConfig, config: dict, out: Path, indices: list[int], variant: str,
             workers: int) -> tuple[Iterator[worker.Result], Any]:
    """The worker results of samples ``indices``, in order, and the process pool making them (None
    when this process makes them): one task a sample, or a sequence in a sequence run, so that one
    worker makes all its frames. ``config`` is ``cfg`` as the run's JSON (:func:`cfg_json`, the
    writer's ``config``), which the workers load."""
    init = (config, str(out), variant, max(1, (os.cpu_count() or 1) // workers))
    if not indices:  # a resumed run that is already complete: nothing to load
        return iter(()), None
    if workers == 1:
        worker.init_worker(*init)
        return map(worker.make_in_process, indices), None
    ctx = mp.get_context("spawn")
    if cfg.sequence.enabled:
        n = cfg.sequence.frames
        pool = ctx.Pool(workers, worker.init_worker, (*init, True), maxtasksperchild=max(1, cfg.render.recycle_after // n))
        return itertools.chain.from_iterable(pool.imap(worker.make_sequence, sorted({i // n for i in indices}))), pool
    pool = ctx.Pool(workers, worker.init_worker, (*init, True), maxtasksperchild=cfg.render.recycle_after)
    return pool.imap(worker.make_one, indices), pool


def cfg_json(cfg: GeneratorConfig) -> dict:
    """The config as the manifest stores it. ``background.align_horizon`` is left out where it
    changes nothing (no plates.json horizons), so that runs made before it resume."""
    d = json.loads(json.dumps(asdict(cfg)))
    if not cfg.sequence.enabled:  # single images: the manifests of before
        d.pop("sequence")
    for key in ("contact_distance", "occupancy"):  # off: the manifests of before these keys
        if not d["labels"][key]:
            d["labels"].pop(key)
    if not cfg.labels.topology and len(d["labels"]) == 2:  # no optional label: the manifests of before
        d.pop("labels")
    if cfg.people.max == 1 and cfg.people.distinct is None:  # one person an image: drawn as before the key
        d["people"].pop("distinct")
    if cfg.people.placement == "apart":  # the placement of before the key
        d["people"].pop("placement")
        d["people"].pop("close")
    if "align_horizon" not in background_kind(cfg.background.kind).records(cfg.background):
        d["background"].pop("align_horizon")
    return d


