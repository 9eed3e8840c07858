"""The Ray engine of ``synth generate --engine ray [--address ADDR]``: one Ray task per shard.

Design (docs/scaling.md has the how-to and the measurements):

- **The driver** (the ``synth generate`` process) does what a local run does first: it checks every
  input file, locks the output folder (:mod:`synth.lock`) and makes the dataset's subjects once,
  into ``DIR/subjects/``. It then submits one task per pending shard and rewrites the manifest as
  shards' checksums come in (at most every ``MANIFEST_EVERY_S``, so that ``--resume`` keeps the
  shards finished before the driver itself was killed), and the final, complete manifest when every
  shard is in.
- **Storage.** ``DIR`` must be a path every node sees under the same name (NFS, Lustre, a mounted
  bucket with rename): tasks read the subjects, the motion library and the backgrounds from there
  and write their shards there. ``fsspec`` URLs (``s3://``) are not supported: a shard appears by an
  atomic rename of its temporary file, which object stores do not offer.
- **A task** makes its shard's samples in index order, in a Ray worker process that loads the
  model, subjects and backgrounds once (:mod:`synth.worker`, as the local process pool's workers do) and keeps its Mitsuba scenes for later tasks of the run
  (replaced after ``render.recycle_after`` images, as local workers are). It writes the shard to
  ``.shard-NNNNNN.tar.<host>.<pid>.tmp`` and renames it, and returns the shard's SHA-256 and size;
  the driver checks that the file it sees has that size before listing the shard (it never reads
  the dataset back; ``--resume`` checks every SHA-256).
- **Faults.** A task whose worker process or node dies is re-run by Ray, up to
  ``engine.max_retries`` times, on any node; the shard it makes is the same bytes, because a
  sample depends on ``(seed, index)`` only. A sample that fails for a data reason (a bad scan, a
  corrupt background) is returned as data, never raised, so Ray does not retry it: with
  ``skip_bad`` it is listed in the manifest, without it the run stops with the one-line error and
  exit status 1 of a local run. A failed write (a full disk) is the local run's one-line error,
  exit status 2.
- **Progress.** Every task reports its images to a counter actor (at most every ``TICK_S``); the
  driver prints one progress line for the whole cluster.
"""

from __future__ import annotations

import json
import os
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from synth import worker
from synth.config import GeneratorConfig
from synth.dataset.shards import ShardWriter, WriteError, shard_name, write_shard
from synth.progress import Progress, log

_KEY: str = ""
TICK_S = 0.25
"""A task reports its progress at most this often (and at its start, its first and its last image)."""
MANIFEST_EVERY_S = 2.0
"""The driver rewrites the manifest at most this often (and at the end): with thousands of shards a
rewrite per shard would be the driver's main work. A driver killed in between loses at most these
seconds of listed shards; ``--resume`` makes them again (the same bytes)."""


def _shard_task(cfg_json: dict, out: str, variant: str, threads: int, shard: int, start: int, stop: int,
                skip_bad: bool, counter: Any) -> dict[str, Any]:
    """Make and write shard ``shard`` (samples ``start .. stop - 1``) in a Ray worker process, with
    the generator's worker (:mod:`synth.worker`).

    Returns:
        ``{"shard", "sha256", "samples", "first", "skipped"}``, or ``{"shard", "error"}`` for a
        sample that failed (without ``skip_bad``), or ``{"shard", "write_error"}``.
    """
    global _KEY
    key = json.dumps([cfg_json, out, variant, threads], sort_keys=True)
    if key != _KEY:  # a new run's settings; within a run make_in_process recycles the worker
        worker.init_worker(cfg_json, out, variant, threads, True)
        _KEY = key
    samples: list[tuple[int, dict[str, bytes]]] = []
    left_out: list[dict[str, Any]] = []
    counter.tick.remote(shard, 0)  # started: a later start of this shard is a retry, even before an image
    last_tick = 0.0
    for i in range(start, stop):
        index, fields, kind, msg = worker.make_in_process(i)
        if i == start or i == stop - 1 or time.time() - last_tick >= TICK_S:
            counter.tick.remote(shard, i - start + 1)
            last_tick = time.time()
        if fields is None:
            if not skip_bad:
                return {"shard": shard, "error": f"sample {i}: {msg}"}
            left_out.append({"index": i, "reason": f"{kind}: {msg}"})
            continue
        samples.append((index, fields))
    path = Path(out) / shard_name(shard)
    try:
        digest = write_shard(path, samples, f"{socket.gethostname() or 'localhost'}.{os.getpid()}")
    except OSError as exc:
        return {"shard": shard, "write_error": str(WriteError.of(path, exc))}
    return {"shard": shard, "sha256": digest, "bytes": path.stat().st_size, "samples": len(samples), "first": start,
            "skipped": left_out}


class _Counter:
    """Images made per shard by its latest attempt (a retried shard starts again from 0), and the
    shards that were started more than once (their worker or node was lost)."""

    def __init__(self) -> None:
        self.made: dict[int, int] = {}
        self.restarted: set[int] = set()

    def tick(self, shard: int, made: int) -> None:
        if made == 0 and shard in self.made:  # a task's first report is at its start
            self.restarted.add(shard)
        self.made[shard] = made

    def total(self) -> int:
        return sum(self.made.values())

    def retried(self) -> list[int]:
        return sorted(self.restarted)


def connect(address: str | None) -> bool:
    """Join the cluster at ``address`` (None: start a local one); True when this call connected
    (the caller then calls ``ray.shutdown()``), False when this process already was.

    Raises:
        ValueError: Ray is not installed, or no cluster answers at ``address``.
    """
    import logging

    try:
        import ray
    except ImportError:
        raise ValueError("--engine ray needs Ray: pip install 'blsm-synth[ray]'") from None
    if ray.is_initialized():
        return False
    _reachable(address)
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # Ray would report usage over the network
    try:
        ray.init(address=address, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR,
                 configure_logging=True)
    except ConnectionError as exc:
        raise ValueError(f"--address {address}: cannot reach a Ray cluster ({str(exc).splitlines()[0]})") from None
    return True


def _reachable(address: str | None, timeout: float = 5.0) -> None:
    """A ValueError unless something answers at ``HOST:PORT`` (Ray's own connection attempt keeps
    retrying for minutes when nothing does). Other address forms are left to Ray."""
    if not address or address == "auto" or "://" in address or ":" not in address:
        return
    host, _, port = address.rpartition(":")
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except ValueError:
        raise ValueError(f"--address {address}: not HOST:PORT") from None
    except OSError as exc:
        raise ValueError(f"--address {address}: no Ray cluster answers there ({exc.strerror or exc})") from None


def run_ray(
    cfg: GeneratorConfig,
    cfg_json: dict[str, Any],
    out: Path,
    writer: ShardWriter,
    plan: tuple[list[int], dict[str, Any], list[dict[str, Any]]],
    variant: str,
    meter: Progress,
    on_image: Callable[[int], None] | None,
) -> dict[str, Any]:
    """The shards of :func:`synth.generate.generate` as Ray tasks (module docstring); the manifest.
    This process must be connected to the cluster (:func:`connect`).

    Args:
        cfg_json: ``cfg`` as JSON (what :func:`synth.worker.init_worker` takes).
        plan: the shards to make (all of them are made), the finished ones, their skipped samples.
        meter: the run's progress meter.

    Raises:
        ValueError: a failed write (:class:`WriteError`).
        RuntimeError: a sample failed (without ``skip_bad``), or a task failed more than
            ``engine.max_retries`` times; the finished shards are kept for ``--resume``.
    """
    import ray
    import ray.util.scheduling_strategies

    todo, done, skipped = plan
    done, skipped = dict(done), list(skipped)
    total = sum(len(writer.indices(s)) for s in todo)
    nodes = [n for n in ray.nodes() if n.get("Alive")]
    cpus = int(sum(n.get("Resources", {}).get("CPU", 0) for n in nodes))
    log(f"{total} images in {len(todo)} shards -> {out} (Ray: {len(nodes)} nodes, {cpus} CPUs, "
               f"{cfg.engine.cpus_per_task} per task; Mitsuba {variant})")
    task = ray.remote(_shard_task).options(num_cpus=cfg.engine.cpus_per_task, max_retries=cfg.engine.max_retries,
                                           retry_exceptions=False)
    # The counter lives on the driver's node: it must outlive any node that leaves.
    # (hard affinity: a soft one let Ray place it on another node when the driver's was busy)
    here = ray.util.scheduling_strategies.NodeAffinitySchedulingStrategy(
        ray.get_runtime_context().get_node_id(), soft=False)
    counter = ray.remote(num_cpus=0)(_Counter).options(scheduling_strategy=here).remote()
    cfg_ref, where = ray.put(cfg_json), str(out.resolve())
    refs = {
        task.remote(cfg_ref, where, variant, cfg.engine.cpus_per_task, s, writer.indices(s).start,
                    writer.indices(s).stop, cfg.skip_bad, counter): s
        for s in todo
    }
    waiting, shards_done, last_manifest = list(refs), len(done), 0.0
    try:
        while waiting:
            ready, waiting = ray.wait(waiting, num_returns=len(waiting), timeout=0.5, fetch_local=True)
            made = min(ray.get(counter.total.remote()), total)
            while meter.made < made:
                meter.tick()
                if on_image is not None:
                    on_image(meter.made)
            for ref in sorted(ready, key=refs.__getitem__):
                s = refs[ref]
                try:
                    res = ray.get(ref)
                except ray.exceptions.RayError as exc:
                    raise RuntimeError(f"{out / shard_name(s)}: the Ray task failed after "
                                       f"{cfg.engine.max_retries} retries ({type(exc).__name__})") from None
                if "error" in res:
                    raise RuntimeError(res["error"])
                if "write_error" in res:
                    raise WriteError(res["write_error"])
                # The writer's SHA-256 is trusted; the driver checks presence and size only, so
                # that it never reads the whole dataset back (--resume re-reads every shard).
                path = out / shard_name(s)
                if not path.is_file() or path.stat().st_size != res["bytes"]:
                    raise RuntimeError(f"{path}: the shard a task wrote is not here or differs "
                                       "(is --out on storage every node sees?)")
                done[shard_name(s)] = {k: res[k] for k in ("sha256", "samples", "first")}
                skipped += res["skipped"]
                if time.time() - last_manifest >= MANIFEST_EVERY_S:
                    writer.write_manifest(done, skipped)
                    last_manifest = time.time()
                shards_done += 1
                meter.shard(writer.progress_line(s, res["samples"], shards_done))
        retried = ray.get(counter.retried.remote())
        if retried:
            log(f"{len(retried)} shards made again after their worker or node was lost: "
                       + ", ".join(shard_name(x) for x in retried))
    finally:
        for ref in waiting:
            ray.cancel(ref, force=True)
        ray.kill(counter)
        _remove_dead_temporaries(out, done)
        man = writer.write_manifest(done, skipped)  # what is finished, also when the run stops
    meter.close()
    return man


def _remove_dead_temporaries(out: Path, done: dict[str, Any]) -> None:
    """Remove the temporary files of finished shards: left by attempts whose process or node died
    while writing (the shard was then made again by a retry)."""
    import glob

    for name in done:
        for p in out.glob(f".{glob.escape(name)}.*.tmp"):
            p.unlink(missing_ok=True)

