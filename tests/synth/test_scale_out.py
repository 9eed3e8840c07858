"""Scale-out (issue 19): partitioned runs joined by ``synth merge``, and the Ray engine on a local
two-node cluster, each giving the same bytes as ``synth generate --workers 2``.

The Ray runs happen in ``tests/synth/ray_scenarios.py`` inside a network namespace that has only
loopback (``unshare -n``), so that Ray, which binds the host's address otherwise, sends nothing
beyond 127.0.0.1; they are skipped, saying why, where such a namespace cannot be made.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from synth.cli import main
from synth.config import load_config
from synth.generate import generate

ROOT = Path(__file__).resolve().parents[2]
CONFIG = """seed: 7
num: 24
subjects: {count: 2, texture_size: 128}
people: {min: 1, max: 2}
camera: {width: 64, height: 64, rare_rate: 0.2, truncation_rate: 0.3}
background: {env_width: 128}
render: {spp: 4}
output: {shard_size: 4}
"""


def files(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (hidden ones included) by relative path."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def assert_same_dataset(a: Path, b: Path) -> None:
    fa, fb = files(a), files(b)
    assert sorted(fa) == sorted(fb), sorted(set(fa) ^ set(fb))
    differ = [k for k in fa if fa[k] != fb[k]]
    assert not differ, differ


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("cfg") / "scale.yaml"
    path.write_text(CONFIG)
    return path


@pytest.fixture(scope="module")
def reference(config, tmp_path_factory) -> Path:
    """``synth generate CONFIG --workers 2``: 24 images in 6 shards."""
    out = tmp_path_factory.mktemp("ref") / "ds"
    generate(load_config(config), out, workers=2, progress=False)
    return out


def _with_subjects(reference: Path, out: Path) -> Path:
    out.mkdir(parents=True)
    shutil.copytree(reference / "subjects", out / "subjects")
    return out


def test_parts_then_merge_give_the_same_dataset(config, reference, tmp_path, capsys):
    out = _with_subjects(reference, tmp_path / "ds")
    cfg = load_config(config)
    generate(cfg, out, part=(1, 3), progress=False)
    generate(cfg, out, part=(3, 3), progress=False)
    assert sorted(p.name for p in out.glob("manifest*")) == ["manifest-part-1-of-3.json", "manifest-part-3-of-3.json"]
    # A part missing: one line naming it, exit 2, nothing changed.
    before = files(out)
    capsys.readouterr()
    assert main(["merge", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"synth: error: {out / 'manifest-part-2-of-3.json'}: missing (part 2/3 has not run here)"]
    assert files(out) == before
    # The same part again without --resume is refused; with it, nothing is remade.
    capsys.readouterr()
    assert main(["generate", str(config), "--out", str(out), "--part", "1/3"]) == 2
    assert "already holds part 1/3 of a dataset" in capsys.readouterr().err
    generate(cfg, out, part=(2, 3), progress=False)
    generate(cfg, out, part=(1, 3), resume=True, progress=False)
    assert main(["merge", str(out)]) == 0
    assert_same_dataset(out, reference)


def test_a_part_run_twice_with_another_n_is_refused_at_the_join(config, reference, tmp_path, capsys):
    out = _with_subjects(reference, tmp_path / "ds")
    cfg = load_config(config)
    for i in (1, 2):
        generate(cfg, out, part=(i, 2), progress=False)
    generate(cfg, out, part=(2, 3), resume=True, progress=False)  # shards 1 and 4, already made by 2/2
    before = files(out)
    capsys.readouterr()
    assert main(["merge", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"synth: error: {out / 'manifest-part-2-of-3.json'}: claims shard-000001.tar"), err
    assert files(out) == before


def test_parts_running_at_the_same_time_into_one_folder(config, reference, tmp_path):
    """Two processes, parts 1/2 and 2/2, started together into a new folder: the subjects are
    made once (by the first part; the other waits for them or finds them made); merged, the same
    bytes as one machine with those subjects. (Subjects are compared with a run of their own:
    their fit depends on the process' torch thread count, which earlier tests of a session set.)"""
    out = tmp_path / "ds"
    cmd = [sys.executable, "-m", "synth.cli", "generate", str(config), "--out", str(out), "--workers", "1"]
    procs = [subprocess.Popen([*cmd, "--part", f"{i}/2"], stderr=subprocess.PIPE, text=True) for i in (1, 2)]
    errs = [p.communicate(timeout=300)[1] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], errs
    made = [line for e in errs for line in e.splitlines() if re.match(r"\[synth\] subject \d+/2 anny_", line)]
    assert len(made) == 2, errs  # two subjects, each made once
    assert main(["merge", str(out)]) == 0
    one = _with_subjects(out, tmp_path / "one")
    generate(load_config(config), one, workers=2, progress=False)
    assert_same_dataset(out, one)


def _can_unshare() -> str:
    try:
        r = subprocess.run(["unshare", "-n", "sh", "-c", "ip link set lo up"], capture_output=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"cannot make a network namespace ({exc})"
    if r.returncode != 0:
        return f"cannot make a network namespace with loopback (unshare -n: {r.stderr.decode().strip()[:200]})"
    try:
        import ray  # noqa: F401
    except ImportError:
        return "Ray is not installed (pip install 'blsm-synth[ray]')"
    return ""


@pytest.mark.skipif(bool(_can_unshare()), reason=_can_unshare() or "ok")
def test_ray_cluster_of_two_nodes_makes_the_same_bytes(config, reference, tmp_path):
    """Two 1-CPU nodes: a plain run; one with a node removed once its worker is in a shard (its
    tasks re-run on the other); one whose driver is killed after its first shard, then resumed; a
    sample failing for a data reason, without and with skip_bad."""
    script = ROOT / "tests" / "synth" / "ray_scenarios.py"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "RAY_USAGE_STATS_ENABLED": "0"}
    cmd = f"ip link set lo up && exec {sys.executable} {script} {config} {reference} {tmp_path}"
    try:
        r = subprocess.run(["unshare", "-n", "sh", "-c", cmd], capture_output=True, text=True, timeout=420, env=env)
    except subprocess.TimeoutExpired as exc:  # where it was: the script's progress lines
        err = exc.stderr.decode() if isinstance(exc.stderr, bytes) else (exc.stderr or "")
        pytest.fail(f"ray_scenarios.py ran out of 420 s; its stderr ends:\n{err[-3000:]}")
    assert r.returncode == 0, r.stderr[-3000:]
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert summary["b_removed_at_image"] is not None and summary["b_removed_at_image"] < 24, summary
    assert summary["b_nodes_alive_after"] == 1, summary
    assert len(summary["b_retried"]) == 1 and "after their worker or node was lost" in summary["b_retried"][0], summary
    assert 1 <= summary["c_shards_when_killed"] < 6, summary
    for run in ("a", "b", "c"):
        assert_same_dataset(tmp_path / run, reference)
    # A data fault is not retried: without skip_bad one line, as a local run; with it, listed.
    assert summary["d_error"] == "sample 5: /data/scans/x/scan.ply: injected data fault", summary
    assert "shard-000001.tar" not in summary["d_manifest_shards"]
    assert summary["e_skipped"] == [{"index": 5, "reason": "ValueError: /data/scans/x/scan.ply: injected data fault"}]
    assert summary["attempts_of_sample_5"] == 2, summary  # once in d, once in e
    ref, e = files(reference), files(tmp_path / "e")
    assert [k for k in ref if k.startswith("shard-") and ref[k] != e[k]] == ["shard-000001.tar"]


def test_a_shard_started_again_is_a_retry_even_before_its_first_image():
    """The Ray engine's counter (a plain class; Ray makes it an actor): a task killed while making
    its first image has reported its start only; its re-run is still listed as made again."""
    from synth.engine_ray import _Counter

    def ticks(c: _Counter, reports: list[tuple[int, int]]) -> _Counter:
        for shard, made in reports:
            c.tick(shard, made)
        return c

    c = ticks(_Counter(), [(0, 0), (1, 0), (1, 1), (1, 4), (0, 0)])  # shard 0 lost before an image, 1 done
    assert c.retried() == [0] and c.total() == 4
    ticks(c, [(0, 1), (2, 0), (2, 1)])  # shard 2 starts once: no retry
    assert c.retried() == [0] and c.total() == 6
