"""Ray scenarios of tests/synth/test_scale_out.py, run in a network namespace with loopback only.

    unshare -n sh -c 'ip link set lo up && python tests/synth/ray_scenarios.py CONFIG REF WORK'

On a local two-node cluster (``ray.cluster_utils.Cluster``, 1 CPU each): (a) the dataset of CONFIG
made with ``--engine ray``; (b) the same with the node the driver is not attached to removed once
its worker is in a shard (its tasks are re-run on the head); (c) a driver killed with SIGKILL after
its first shard, then ``--resume``. (d) sample 5 failing for a data reason in the workers, and (e) the same with skip_bad. Every run
starts from REF's subjects (copied), and writes into WORK/{a,b,c,d,e}. Prints a JSON summary.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path


def break_sample_5() -> None:
    """Ray worker setup hook: sample 5 raises a ValueError, as a bad input file would; each
    attempt is logged to $BREAK_LOG."""
    from synth import sample as gen

    make = gen.SampleMaker.make

    def broken(self, index, rng):
        if index == 5:
            with open(os.environ["BREAK_LOG"], "a") as fh:
                fh.write(f"{os.getpid()}\n")
            raise ValueError("/data/scans/x/scan.ply: injected data fault")
        return make(self, index, rng)

    gen.SampleMaker.make = broken


def slow_samples() -> None:
    """Ray worker setup hook: every sample takes 0.3 s longer; each sample's start is logged as the
    worker's pid to $START_LOG."""
    from synth import sample as gen

    make = gen.SampleMaker.make

    def slow(self, index, rng):
        with open(os.environ["START_LOG"], "a") as fh:
            fh.write(f"{os.getpid()}\n")
        time.sleep(0.3)
        return make(self, index, rng)

    gen.SampleMaker.make = slow


def hook_env(hook: str, work: Path) -> dict:
    """A runtime environment whose worker processes run ``hook`` at start-up."""
    return {"worker_process_setup_hook": hook,
            "env_vars": {"PYTHONPATH": f"{Path(__file__).parent}:{Path(__file__).parents[2]}",
                         "BREAK_LOG": str(work / "attempts.txt"), "START_LOG": str(work / "starts.txt")}}


def workers_of(node) -> list[int]:
    """The worker processes of a ``ray.cluster_utils`` node: the children of its raylet."""
    arg = f"--raylet_socket_name={node.raylet_socket_name}"
    raylets = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if arg.encode() in cmd:
            raylets.append(int(pid))
    children = []
    for raylet in raylets:
        for task in Path(f"/proc/{raylet}/task").glob("*"):
            try:
                children += [int(c) for c in (task / "children").read_text().split()]
            except OSError:  # a thread that ended meanwhile
                continue
    return children


def kill_workers_of(node) -> int:
    """SIGKILL the worker processes of a ``ray.cluster_utils`` node; return how many."""
    killed = 0
    for child in workers_of(node):
        try:
            os.kill(child, signal.SIGKILL)
            killed += 1
        except ProcessLookupError:
            pass
    return killed


def in_a_shard(node, work: Path) -> bool:
    """Whether one of the node's live workers has started a sample (``slow_samples``' log)."""
    log = work / "starts.txt"
    if not log.is_file():
        return False
    pids = set(workers_of(node))
    return any(int(p) in pids for p in log.read_text().split())


_START = time.time()


def _say(what: str) -> None:
    """A progress line on stderr, seconds since the start (the test shows it when the script runs
    out of time)."""
    print(f"[ray_scenarios] {time.time() - _START:6.1f} s {what}", file=sys.stderr, flush=True)


def main() -> None:
    import logging

    import ray
    from ray.cluster_utils import Cluster

    from synth.config import load_config
    from synth.generate import generate

    cfg_path, ref, work = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])
    cfg = load_config(cfg_path)
    t0 = time.time()
    # A dead node is noticed after 3 missed health checks 0.3 s apart (Ray's default waits ~15 s).
    fast = {"health_check_initial_delay_ms": 0, "health_check_period_ms": 300, "health_check_failure_threshold": 3}
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "_system_config": fast})
    worker = cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    ray.init(address=cluster.address, log_to_driver=False, logging_level=logging.ERROR)
    summary: dict = {"cluster_start_s": round(time.time() - t0, 1)}

    def fresh(name: str) -> Path:
        out = work / name
        out.mkdir(parents=True)
        shutil.copytree(ref / "subjects", out / "subjects")
        return out

    _say("cluster up; (a) plain run")
    t0 = time.time()
    generate(cfg, fresh("a"), engine="ray", progress=False)
    summary["a_s"] = round(time.time() - t0, 1)

    removed: dict = {}

    def remove_node(made: int) -> None:
        # Once the victim's worker is inside a shard (its first sample started), about 0.5 s in
        # on an idle machine; on a busy one its worker may start later than the head's images.
        if not removed and in_a_shard(victim, work):
            removed["at_image"] = made
            # Its worker processes die with it, mid-shard (left alone, a worker whose raylet died
            # can still finish its task and hand the result to the driver).
            removed["workers_killed"] = kill_workers_of(victim)
            cluster.remove_node(victim, allow_graceful=False)

    t0 = time.time()
    ray.shutdown()  # a driver whose workers take 0.3 s more per sample: every shard lasts over 1 s
    ray.init(address=cluster.address, log_to_driver=False, logging_level=logging.ERROR,
             runtime_env=hook_env("ray_scenarios.slow_samples", work))
    # Remove the node this driver is not attached to (a driver may attach to either raylet).
    mine = ray.get_runtime_context().get_node_id()
    victim = worker if worker.node_id != mine else cluster.head_node
    summary["removed"] = "worker" if victim is worker else "head"
    _say(f"(b) a node removed, victim {summary['removed']}")
    log = io.StringIO()
    with contextlib.redirect_stderr(log):
        generate(cfg, fresh("b"), engine="ray", progress=False, on_image=remove_node)
    summary.update(b_s=round(time.time() - t0, 1), b_removed_at_image=removed.get("at_image"),
                   b_workers_killed=removed.get("workers_killed"),
                   b_retried=[ln for ln in log.getvalue().splitlines() if "made again" in ln])
    t0 = time.time()
    while sum(bool(n["Alive"]) for n in ray.nodes()) > 1 and time.time() - t0 < 30:
        time.sleep(0.2)
    summary["b_nodes_alive_after"] = sum(bool(n["Alive"]) for n in ray.nodes())

    _say(f"(b) done, node removed at image {removed.get('at_image')}; (c) driver killed, then resumed")
    out = fresh("c")
    driver = subprocess.Popen([sys.executable, "-m", "synth.cli", "generate", str(cfg_path), "--out", str(out),
                               "--engine", "ray", "--address", cluster.address], stderr=subprocess.DEVNULL)
    t0 = time.time()
    while time.time() - t0 < 120:
        man = out / "manifest.json"
        if man.is_file() and json.loads(man.read_text())["shards"]:
            break
        time.sleep(0.05)
    driver.send_signal(signal.SIGKILL)
    driver.wait()
    summary["c_shards_when_killed"] = len(json.loads((out / "manifest.json").read_text())["shards"])
    generate(cfg, out, engine="ray", progress=False, resume=True)

    # (d, e) Sample 5 fails for a data reason in the Ray workers (break_sample_5, a worker setup
    # hook): never retried; without skip_bad the run stops with the local one-line error, with it
    # the sample is listed as skipped.
    _say("(d, e) a data fault")
    ray.shutdown()
    ray.init(address=cluster.address, log_to_driver=False, logging_level=logging.ERROR,
             runtime_env=hook_env("ray_scenarios.break_sample_5", work))
    try:
        generate(cfg, fresh("d"), engine="ray", progress=False)
        summary["d_error"] = None
    except RuntimeError as exc:
        summary["d_error"] = str(exc)
    summary["d_manifest_shards"] = sorted(json.loads((work / "d" / "manifest.json").read_text())["shards"])
    skip = dataclasses.replace(cfg, skip_bad=True)
    man = generate(skip, fresh("e"), engine="ray", progress=False)
    summary["e_skipped"] = man["skipped"]
    summary["attempts_of_sample_5"] = len((work / "attempts.txt").read_text().splitlines())
    ray.shutdown()
    cluster.shutdown()
    _say("done")
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
