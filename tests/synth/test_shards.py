"""Shards: atomic, byte-reproducible, resumable to the same dataset, seeded per (seed, index)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from synth.dataset.shards import (
    MANIFEST,
    ShardWriter,
    SkipSample,
    read_shard,
    sample_key,
    sample_rng,
    sha256_file,
    shard_name,
    write_shard,
)


def make_sample(index: int, rng: np.random.Generator) -> dict[str, bytes]:
    values = rng.normal(size=8)
    return {
        "json": json.dumps({"index": index, "values": values.tolist()}).encode(),
        "noise.npy": values.astype("<f4").tobytes(),
    }


def writer(tmp_path, name="ds", **kw):
    args = dict(num=23, shard_size=5, seed=7, config={"pipeline": "test"}, versions={"numpy": np.__version__})
    args.update(kw)
    return ShardWriter(out=tmp_path / name, **args)


def test_sample_rng_depends_on_seed_and_index_only():
    a = sample_rng(3, 10).normal(size=4)
    np.testing.assert_array_equal(a, sample_rng(3, 10).normal(size=4))
    assert not np.allclose(a, sample_rng(3, 11).normal(size=4))
    assert not np.allclose(a, sample_rng(4, 10).normal(size=4))
    with pytest.raises(ValueError):
        sample_rng(-1, 0)


def test_shards_hold_every_sample_once_in_webdataset_layout(tmp_path):
    man = writer(tmp_path).run(make_sample)
    assert man["complete"] and man["num_samples"] == 23
    assert sorted(man["shards"]) == [shard_name(s) for s in range(5)]
    seen = []
    for name, entry in man["shards"].items():
        samples = read_shard(tmp_path / "ds" / name)
        assert len(samples) == entry["samples"]
        assert sha256_file(tmp_path / "ds" / name) == entry["sha256"]
        for key, fields in samples.items():
            assert set(fields) == {"json", "noise.npy"}
            meta = json.loads(fields["json"])
            assert key == sample_key(meta["index"])
            np.testing.assert_array_equal(
                np.frombuffer(fields["noise.npy"], "<f4"),
                sample_rng(7, meta["index"]).normal(size=8).astype("<f4"),
            )
            seen.append(meta["index"])
    assert sorted(seen) == list(range(23))
    assert not list((tmp_path / "ds").glob(".*tmp"))


def test_interrupted_and_resumed_run_equals_an_uninterrupted_one(tmp_path):
    full = writer(tmp_path, "full").run(make_sample)
    part = writer(tmp_path, "part")
    first = part.run(make_sample, stop_after=2)
    assert not first["complete"] and len(first["shards"]) == 2
    # A crash mid-shard leaves only a hidden temporary file, which resume ignores and replaces.
    (tmp_path / "part" / f".{shard_name(2)}.tmp").write_bytes(b"half a shard")
    # A damaged finished shard is detected by its checksum and regenerated.
    (tmp_path / "part" / shard_name(1)).write_bytes(b"corrupt")
    resumed = writer(tmp_path, "part").run(make_sample, resume=True)
    assert resumed["complete"]
    assert resumed["shards"] == full["shards"]  # same SHA-256 for every shard
    for name in full["shards"]:
        assert (tmp_path / "full" / name).read_bytes() == (tmp_path / "part" / name).read_bytes()


def test_a_run_stops_where_its_shards_are_chosen(tmp_path):
    """stop_after trims the pending shards (ShardWriter.pending), the one place a run stops early;
    a run given a plan takes no second stop."""
    w = writer(tmp_path)
    todo, done, skipped = w.pending(False)
    assert w.pending(False, stop_after=2) == (todo[:2], done, skipped) and len(todo) > 2
    with pytest.raises(ValueError, match="not both"):
        w.run(make_sample, stop_after=1, plan=(todo, done, skipped))
    assert not (tmp_path / "ds" / MANIFEST).exists()
    man = w.run(make_sample, plan=w.pending(False, stop_after=2))
    assert sorted(man["shards"]) == [shard_name(0), shard_name(1)] and not man["complete"]


def test_refuses_to_overwrite_or_to_resume_a_different_run(tmp_path):
    writer(tmp_path).run(make_sample, stop_after=1)
    with pytest.raises(ValueError, match="already holds a dataset"):
        writer(tmp_path).run(make_sample)
    with pytest.raises(ValueError, match=f"{MANIFEST}: seed differs"):
        writer(tmp_path, seed=8).run(make_sample, resume=True)
    with pytest.raises(ValueError, match="config differs"):
        writer(tmp_path, config={"pipeline": "other"}).run(make_sample, resume=True)


def test_replace_stale_moves_another_runs_dataset_aside_and_keeps_the_same_run(tmp_path):
    """``synth generate --resume --replace-stale`` (make demo after the defaults changed): a dataset
    made with other settings is moved whole to ``ds.stale-<time>`` (nothing deleted); the same run's
    is kept for --resume; no manifest is nothing to move."""
    from synth.generate import set_aside_stale

    assert set_aside_stale(writer(tmp_path)) is None  # an empty folder
    writer(tmp_path).run(make_sample, stop_after=2)
    (tmp_path / "ds" / "subjects").mkdir()
    (tmp_path / "ds" / "subjects" / "mine.txt").write_text("a user's file")
    before = {p.relative_to(tmp_path / "ds"): p.read_bytes() for p in (tmp_path / "ds").rglob("*") if p.is_file()}
    assert set_aside_stale(writer(tmp_path)) is None  # the same run: left for --resume
    aside = set_aside_stale(writer(tmp_path, config={"pipeline": "other"}))
    assert aside is not None and aside.parent == tmp_path and aside.name.startswith("ds.stale-")
    assert list((tmp_path / "ds").iterdir()) == []  # no lock file left behind either
    after = {p.relative_to(aside): p.read_bytes() for p in aside.rglob("*") if p.is_file()}
    assert after == before
    man = writer(tmp_path, config={"pipeline": "other"}).run(make_sample, resume=True)
    assert man["complete"] and len(man["shards"]) == 5
    (tmp_path / "ds" / MANIFEST).write_text("{")
    with pytest.raises(ValueError, match=f"{MANIFEST}: unreadable manifest"):
        set_aside_stale(writer(tmp_path, seed=9))


def test_failed_sample_leaves_no_shard(tmp_path):
    def bad(index, rng):
        if index == 3:
            raise RuntimeError("render failed")
        return make_sample(index, rng)

    w = writer(tmp_path)
    with pytest.raises(RuntimeError):
        w.run(bad)
    assert not (tmp_path / "ds" / shard_name(0)).exists()
    assert not list((tmp_path / "ds").glob("*.tmp")) and not list((tmp_path / "ds").glob(".*.tmp"))
    with pytest.raises(ValueError, match="bad field name"):
        write_shard(tmp_path / "x.tar", [(0, {"a/b": b"1"})])
    assert not (tmp_path / "x.tar").exists()


def test_skipped_samples_are_left_out_and_listed_across_a_resume(tmp_path):
    def skip_seven(index, rng):
        if index == 7:
            raise SkipSample("unlucky")
        return make_sample(index, rng)

    w = writer(tmp_path)
    w.run(skip_seven, stop_after=2)
    man = writer(tmp_path).run(skip_seven, resume=True)
    assert man["complete"] and man["skipped"] == [{"index": 7, "reason": "unlucky"}]
    assert man["shards"][shard_name(1)]["samples"] == 4
    assert sample_key(7) not in read_shard(tmp_path / "ds" / shard_name(1))
    assert sum(e["samples"] for e in man["shards"].values()) == 22
