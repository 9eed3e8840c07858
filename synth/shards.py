"""WebDataset-compatible tar shards, a manifest, per-sample seeding, and resumable runs.

A dataset folder holds ``shard-000000.tar``, ``shard-000001.tar``, ... and ``manifest.json``.
Shard ``s`` holds the samples with indices ``s * shard_size ... (s + 1) * shard_size - 1`` (the last
one fewer). A sample is a group of tar members sharing one key, ``f"{index:09d}"``, each member
named ``<key>.<field>`` (``000000042.rgb.png``, ``000000042.json``, ...), the WebDataset layout.

Guarantees:

- A shard appears only when complete: it is written to a hidden temporary file beside it
  (``.shard-000000.tar.<tag>.tmp``, the tag naming its writer, see :mod:`synth.lock`) and renamed.
- A write that fails (a full disk: ``ENOSPC``) removes its temporary file and stops the run with
  a ValueError naming the path (:class:`WriteError`); the shards already finished and the manifest
  listing them stay valid, so ``--resume`` after freeing space makes the same bytes.
- Shards are as reproducible as their samples: members are written in sorted order with fixed
  metadata (mtime 0, uid/gid 0, mode 0644), and a sample's randomness comes only from
  :func:`sample_rng` with ``(seed, index)``, so equal sample bytes give equal shard bytes and a
  resumed run gives the same dataset as an uninterrupted one (for the generator's rare RGB
  exception see :func:`synth.render.PeopleRenderer.render`).
- The manifest (written atomically after every shard) records the config, the seed, package
  versions, counts and the SHA-256 of every finished shard. :func:`ShardWriter.resume` keeps the
  shards whose checksum matches and regenerates the rest.
"""

from __future__ import annotations

import errno
import glob
import io
import json
import tarfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from blsm.io import atomic_write, sha256_file

MANIFEST = "manifest.json"
FORMAT = "blsm-synth-shards"
VERSION = 1


class SkipSample(Exception):
    """Raised by a ``make_sample`` callable to leave that sample out (the message is the reason)."""


class WriteError(ValueError):
    """Writing the dataset failed (a full disk, a read-only folder): one line naming the path."""

    @classmethod
    def of(cls, path: Path, exc: OSError) -> WriteError:
        why = "no space left on device" if exc.errno in (errno.ENOSPC, errno.EDQUOT) else (exc.strerror or str(exc))
        return cls(f"{path}: cannot write ({why}); the finished shards are kept, continue with --resume")


def sample_key(index: int) -> str:
    """The WebDataset key of sample ``index``."""
    return f"{index:09d}"


def shard_name(shard: int) -> str:
    return f"shard-{shard:06d}.tar"


def sample_rng(seed: int, index: int) -> np.random.Generator:
    """The random generator of one sample: a function of ``(seed, index)`` only.

    Independent streams for different indices (``numpy.random.SeedSequence`` spawning), so samples
    can be made in any order, by any worker, and a resumed run repeats them exactly.
    """
    if seed < 0 or index < 0:
        raise ValueError(f"seed and index must be non-negative, got {seed}, {index}")
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), int(index)])))


def _write_json_atomic(path: Path, obj: Any, tag: str = "") -> None:
    with atomic_write(path, "w", tag) as f:
        f.write(json.dumps(obj, indent=1, sort_keys=True) + "\n")


def _add_member(tar: tarfile.TarFile, name: str, data: bytes) -> None:
    info = tarfile.TarInfo(name)
    info.size = len(data)
    info.mtime = 0
    info.mode = 0o644
    info.uid = info.gid = 0
    info.uname = info.gname = ""
    tar.addfile(info, io.BytesIO(data))


def write_shard(path: str | Path, samples: Iterable[tuple[int, dict[str, bytes]]], tag: str = "") -> str:
    """Write one shard atomically; return its SHA-256.

    Args:
        path: the final ``.tar`` path; the data goes to a hidden ``.<tag>.tmp`` file first.
        samples: ``(index, {field: bytes})`` pairs; fields are e.g. ``"rgb.png"``, ``"json"``.
        tag: the writer's mark in the temporary name (:attr:`synth.lock.OutputLock.tag`).

    Raises:
        ValueError: on a field name with a ``/`` or an empty sample; nothing is left behind.
    """
    path = Path(path)
    with atomic_write(path, tag=tag) as f, tarfile.open(fileobj=f, mode="w", format=tarfile.USTAR_FORMAT) as tar:
        for index, fields in samples:
            if not fields:
                raise ValueError(f"sample {index} has no fields")
            key = sample_key(index)
            for name in sorted(fields):
                if "/" in name or not name:
                    raise ValueError(f"sample {index}: bad field name {name!r}")
                _add_member(tar, f"{key}.{name}", fields[name])
    return sha256_file(path)


def read_shard(path: str | Path) -> dict[str, dict[str, bytes]]:
    """All samples of a shard as ``{key: {field: bytes}}`` (for tests, validation and loaders)."""
    path = Path(path)
    out: dict[str, dict[str, bytes]] = {}
    try:
        with tarfile.open(path, mode="r") as tar:
            for m in tar:
                if not m.isfile():
                    continue
                key, _, name = m.name.partition(".")
                data = tar.extractfile(m)
                assert data is not None
                out.setdefault(key, {})[name] = data.read()
    except (OSError, tarfile.TarError) as exc:
        raise ValueError(f"{path}: not a readable shard ({exc})") from None
    return out


@dataclass
class ShardWriter:
    """Generate a dataset of ``num`` samples into ``out`` in shards, resumably.

    Args:
        out: dataset folder.
        num: number of samples.
        shard_size: samples per shard.
        seed: the dataset seed (passed to :func:`sample_rng` with each index).
        config: the configuration, recorded in the manifest (JSON-serialisable).
        versions: package versions, recorded in the manifest.
        tag: the writer's mark in its temporary file names (:mod:`synth.lock`).
    """

    out: Path
    num: int
    shard_size: int
    seed: int
    config: dict[str, Any] = field(default_factory=dict)
    versions: dict[str, str] = field(default_factory=dict)
    tag: str = ""

    def __post_init__(self) -> None:
        self.out = Path(self.out)
        if self.num < 1 or self.shard_size < 1:
            raise ValueError(f"num and shard_size must be positive, got {self.num}, {self.shard_size}")

    @property
    def num_shards(self) -> int:
        return -(-self.num // self.shard_size)

    def indices(self, shard: int) -> range:
        return range(shard * self.shard_size, min((shard + 1) * self.shard_size, self.num))

    def manifest(self, shards: dict[str, Any], skipped: list[dict[str, Any]] | None = None) -> dict[str, Any]:
        """The manifest for the finished ``shards`` (name -> entry) and the ``skipped`` samples."""
        return {
            "format": FORMAT,
            "version": VERSION,
            "seed": self.seed,
            "num_samples": self.num,
            "shard_size": self.shard_size,
            "config": self.config,
            "versions": self.versions,
            "shards": shards,
            "complete": len(shards) == self.num_shards,
            "skipped": sorted(skipped or [], key=lambda e: e["index"]),
        }

    def write_manifest(self, shards: dict[str, Any], skipped: list[dict[str, Any]] | None = None) -> dict[str, Any]:
        """Write :meth:`manifest` atomically to ``out/manifest.json``; return it."""
        man = self.manifest(dict(sorted(shards.items())), skipped)
        try:
            _write_json_atomic(self.out / MANIFEST, man, self.tag)
        except OSError as exc:
            raise WriteError.of(self.out / MANIFEST, exc) from None
        return man

    def pending(self, resume: bool) -> tuple[list[int], dict[str, Any], list[dict[str, Any]]]:
        """The shards still to make, the finished ones' manifest entries, and the samples the
        manifest lists as skipped in those finished shards.

        Without ``resume`` the folder must not hold a dataset yet. With it, the manifest must
        describe the same run (seed, count, shard size, config); a shard is kept only when its file
        exists and its SHA-256 matches.
        """
        man_path = self.out / MANIFEST
        if not resume:
            if man_path.exists() or any(self.out.glob("shard-*.tar")):
                raise ValueError(f"{self.out}: already holds a dataset; use --resume or another --out")
            return list(range(self.num_shards)), {}, []
        if not man_path.exists():
            return list(range(self.num_shards)), {}, []
        try:
            man = json.loads(man_path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"{man_path}: unreadable manifest ({exc})") from None
        for key, mine in (
            ("seed", self.seed),
            ("num_samples", self.num),
            ("shard_size", self.shard_size),
            ("config", self.config),
        ):
            if man.get(key) != mine:
                raise ValueError(f"{man_path}: {key} differs from this run; cannot resume into it")
        done: dict[str, Any] = {}
        for name, entry in (man.get("shards") or {}).items():
            p = self.out / name
            if p.is_file() and sha256_file(p) == entry.get("sha256"):
                done[name] = entry
        todo = [s for s in range(self.num_shards) if shard_name(s) not in done]
        kept = {i for s in range(self.num_shards) if shard_name(s) in done for i in self.indices(s)}
        skipped = [e for e in man.get("skipped", []) if e.get("index") in kept]
        return todo, done, skipped

    def run(
        self,
        make_sample: Callable[[int, np.random.Generator], dict[str, bytes]],
        resume: bool = False,
        on_shard: Callable[[int, int], None] | None = None,
        stop_after: int | None = None,
        plan: tuple[list[int], dict[str, Any], list[dict[str, Any]]] | None = None,
    ) -> dict[str, Any]:
        """Make every pending shard; return the final manifest.

        Args:
            make_sample: ``(index, rng) -> {field: bytes}``; ``rng`` is ``sample_rng(seed, index)``.
                Raising :class:`SkipSample` leaves the sample out of its shard and lists it, with
                the reason, in the manifest's ``skipped``.
            resume: continue a previous run into the same folder.
            on_shard: optional ``(shard, samples_in_it)`` callback after each shard (progress).
            stop_after: stop after this many shards (simulates an interruption in tests).
            plan: what :meth:`pending` returned, when the caller checked the folder before
                starting (``resume`` is then not looked at).
        """
        try:
            self.out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise WriteError.of(self.out, exc) from None
        todo, done, skipped = plan if plan is not None else self.pending(resume)
        skipped = list(skipped)
        for count, s in enumerate(todo):
            if stop_after is not None and count >= stop_after:
                break
            idx, left_out = self.indices(s), []
            path = self.out / shard_name(s)
            try:
                digest = write_shard(path, self._samples(make_sample, idx, left_out), self.tag)
            except OSError as exc:
                raise WriteError.of(path, exc) from None
            skipped += left_out
            done[shard_name(s)] = {"sha256": digest, "samples": len(idx) - len(left_out), "first": idx.start}
            self.write_manifest(done, skipped)
            if on_shard is not None:
                on_shard(s, len(idx) - len(left_out))
        return self.write_manifest(done, skipped)

    def temporary_files(self, tag: str) -> list[Path]:
        """The temporary files a writer with ``tag`` left in the folder (a dead writer's)."""
        return sorted(p for p in self.out.glob(f".*.{glob.escape(tag)}.tmp") if p.is_file()) if tag else []

    def _samples(
        self, make_sample: Callable[[int, np.random.Generator], dict[str, bytes]], idx: range, left_out: list
    ) -> Iterator[tuple[int, dict[str, bytes]]]:
        for i in idx:
            try:
                fields = make_sample(i, sample_rng(self.seed, i))
            except SkipSample as exc:
                left_out.append({"index": i, "reason": str(exc)})
                continue
            except OSError as exc:  # the sample's own failure, not a write of this shard
                raise RuntimeError(f"sample {i}: {exc}") from exc
            yield i, fields
