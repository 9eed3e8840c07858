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

**Parts.** A run of part ``I`` of ``N`` (``synth generate --part I/N``, for job arrays and loops over
machines) makes the shards ``s`` with ``s % N == I - 1`` and records them in its own manifest,
``manifest-part-I-of-N.json``; parts may run at the same time into one folder. :func:`merge_parts`
(``synth merge DIR``) checks that the N part manifests are all there, describe the same run, claim
disjoint shards that cover the dataset, and that every shard's SHA-256 matches; it then writes
``manifest.json`` (the same bytes a one-machine run writes) and removes the part manifests.
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
RUN_INDEPENDENT = ("engine",)
"""Config sections that do not change a byte of the data (how shards are distributed): ignored
when a manifest is compared with a run (resume, merge)."""


def part_manifest_name(part: int, parts: int) -> str:
    """``manifest.json`` for the whole run, ``manifest-part-I-of-N.json`` for part ``I`` of ``N``."""
    return MANIFEST if parts == 1 else f"manifest-part-{part}-of-{parts}.json"


def parse_part(text: str) -> tuple[int, int]:
    """``"I/N"`` to ``(I, N)`` with ``1 <= I <= N``; a ValueError otherwise."""
    try:
        i, n = (int(x) for x in text.split("/"))
    except ValueError:
        raise ValueError(f"--part must be I/N (e.g. 2/8), got {text!r}") from None
    if not 1 <= i <= n:
        raise ValueError(f"--part {text}: I must be in [1, N]")
    return i, n


def _data_config(config: Any) -> Any:
    """The config without :data:`RUN_INDEPENDENT` sections."""
    return {k: v for k, v in config.items() if k not in RUN_INDEPENDENT} if isinstance(config, dict) else config


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
        part: ``(I, N)``: this writer makes part ``I`` of ``N`` (module docstring); ``(1, 1)`` is
            the whole dataset.
    """

    out: Path
    num: int
    shard_size: int
    seed: int
    config: dict[str, Any] = field(default_factory=dict)
    versions: dict[str, str] = field(default_factory=dict)
    tag: str = ""
    part: tuple[int, int] = (1, 1)

    def __post_init__(self) -> None:
        self.out = Path(self.out)
        if self.num < 1 or self.shard_size < 1:
            raise ValueError(f"num and shard_size must be positive, got {self.num}, {self.shard_size}")
        self.part = (int(self.part[0]), int(self.part[1]))
        if not 1 <= self.part[0] <= self.part[1]:
            raise ValueError(f"part must be I/N with 1 <= I <= N, got {self.part}")

    @property
    def num_shards(self) -> int:
        return -(-self.num // self.shard_size)

    @property
    def manifest_path(self) -> Path:
        return self.out / part_manifest_name(*self.part)

    @property
    def part_label(self) -> str:
        """``"part I/N"``, or ``""`` for the whole dataset."""
        return f"part {self.part[0]}/{self.part[1]}" if self.part[1] > 1 else ""

    def progress_line(self, shard: int, count: int, shards_done: int) -> str:
        """The progress line of a finished shard: ``shard-NNNNNN.tar: C samples (D/T shards[, part I/N])``."""
        where = f", {self.part_label}" if self.part_label else ""
        return f"{shard_name(shard)}: {count} samples ({shards_done}/{len(self.shards())} shards{where})"

    def shards(self) -> list[int]:
        """The shards this writer makes: all, or those with ``s % N == I - 1`` for part ``I/N``."""
        i, n = self.part
        return [s for s in range(self.num_shards) if s % n == i - 1]

    def indices(self, shard: int) -> range:
        return range(shard * self.shard_size, min((shard + 1) * self.shard_size, self.num))

    def manifest(self, shards: dict[str, Any], skipped: list[dict[str, Any]] | None = None) -> dict[str, Any]:
        """The manifest for the finished ``shards`` (name -> entry) and the ``skipped`` samples."""
        man = {
            "format": FORMAT,
            "version": VERSION,
            "seed": self.seed,
            "num_samples": self.num,
            "shard_size": self.shard_size,
            "config": self.config,
            "versions": self.versions,
            "shards": shards,
            "complete": len(shards) == len(self.shards()),
            "skipped": sorted(skipped or [], key=lambda e: e["index"]),
        }
        if self.part[1] > 1:
            man["part"] = list(self.part)
        return man

    def write_manifest(self, shards: dict[str, Any], skipped: list[dict[str, Any]] | None = None) -> dict[str, Any]:
        """Write :meth:`manifest` atomically to :attr:`manifest_path`; return it."""
        man = self.manifest(dict(sorted(shards.items())), skipped)
        try:
            _write_json_atomic(self.manifest_path, man, self.tag)
        except OSError as exc:
            raise WriteError.of(self.manifest_path, exc) from None
        return man

    def same_run(self, man: Any, man_path: Path, what: str = "cannot resume into it") -> None:
        """A ValueError naming ``man_path`` unless manifest ``man`` describes this run (format,
        seed, count, shard size, and the config up to :data:`RUN_INDEPENDENT` sections)."""
        if not isinstance(man, dict) or man.get("format") != FORMAT:
            raise ValueError(f"{man_path}: not a {FORMAT!r} manifest")
        for key, mine in (
            ("seed", self.seed),
            ("num_samples", self.num),
            ("shard_size", self.shard_size),
            ("config", _data_config(self.config)),
        ):
            theirs = _data_config(man.get(key)) if key == "config" else man.get(key)
            if theirs != mine:
                raise ValueError(f"{man_path}: {key} differs from this run; {what}")

    def read_manifest(self) -> Any:
        """The parsed :attr:`manifest_path`, or None when there is none; a ValueError naming it when
        it cannot be read or parsed."""
        man_path = self.manifest_path
        if not man_path.exists():
            return None
        try:
            return json.loads(man_path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{man_path}: unreadable manifest ({exc})") from None

    def pending(
        self, resume: bool, stop_after: int | None = None
    ) -> tuple[list[int], dict[str, Any], list[dict[str, Any]]]:
        """The shards still to make, the finished ones' manifest entries, and the samples the
        manifest lists as skipped in those finished shards.

        Without ``resume`` the folder must not hold a dataset yet. With it, the manifest must
        describe the same run (seed, count, shard size, config); a shard is kept only when its file
        exists and its SHA-256 matches.

        ``stop_after``: make only the first this many of the shards still to make (the one place
        a run is stopped early: it simulates an interruption in tests).
        """
        todo, done, skipped = self._pending(resume)
        return (todo if stop_after is None else todo[:stop_after]), done, skipped

    def _pending(self, resume: bool) -> tuple[list[int], dict[str, Any], list[dict[str, Any]]]:
        man_path, mine = self.manifest_path, self.shards()
        if not resume:
            if man_path.exists() or any((self.out / shard_name(x)).exists() for x in mine):
                what = f"{self.part_label} of a dataset" if self.part_label else "a dataset"
                raise ValueError(f"{self.out}: already holds {what}; use --resume or another --out")
            if self.part[1] == 1 and any(self.out.glob("manifest-part-*.json")):
                raise ValueError(f"{self.out}: holds parts of a dataset (manifest-part-*.json); run synth merge, "
                                 "or continue the parts with --part I/N --resume")
            return mine, {}, []
        man = self.read_manifest()
        if man is None:
            return mine, {}, []
        self.same_run(man, man_path)
        done: dict[str, Any] = {}
        entries = man.get("shards") or {}
        if not isinstance(entries, dict):
            raise ValueError(f"{man_path}: 'shards' must map each shard's name to its entry")
        for name, entry in entries.items():
            p = self.out / name
            if isinstance(entry, dict) and p.is_file() and sha256_file(p) == entry.get("sha256"):
                done[name] = entry
        todo = [x for x in mine if shard_name(x) not in done]
        kept = {i for x in mine if shard_name(x) in done for i in self.indices(x)}
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
            stop_after: stop after this many shards (:meth:`pending`).
            plan: what :meth:`pending` returned, when the caller checked the folder before
                starting (``resume`` and ``stop_after`` are then not looked at; give neither).
        """
        if plan is not None and (resume or stop_after is not None):
            raise ValueError("give ShardWriter.run a plan, or resume and stop_after for pending(), not both")
        try:
            self.out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise WriteError.of(self.out, exc) from None
        todo, done, skipped = plan if plan is not None else self.pending(resume, stop_after)
        skipped = list(skipped)
        for s in todo:
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


def merge_parts(out: str | Path, tag: str = "") -> dict[str, Any]:
    """Join the part manifests of ``out`` into ``manifest.json`` (module docstring, Parts).

    Args:
        out: the dataset folder.
        tag: the merging writer's mark for its temporary file (:mod:`synth.lock`).

    Returns:
        The merged manifest: the bytes a one-machine run of the same config writes.

    Raises:
        ValueError: one line naming the file: no part manifests; parts of different partitions, or
            two that claim the same shard (a part run twice, with another ``N``); a missing or
            unfinished part; parts of different runs (seed, count, shard size, config); a shard
            missing or whose SHA-256 differs from its part's manifest.
    """
    out = Path(out)
    found = sorted(out.glob("manifest-part-*-of-*.json"))
    if not found:
        raise ValueError(f"{out}: no part manifests (manifest-part-I-of-N.json) to merge")
    parts: dict[tuple[int, int], tuple[Path, dict[str, Any]]] = {}
    owner: dict[str, Path] = {}
    for path in found:
        try:
            man = json.loads(path.read_bytes().decode("utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: unreadable manifest ({exc})") from None
        if not isinstance(man, dict) or man.get("format") != FORMAT or not isinstance(man.get("shards"), dict):
            raise ValueError(f"{path}: not a {FORMAT!r} part manifest")
        try:
            key = parse_part("/".join(str(x) for x in man.get("part", [])))
        except ValueError:
            raise ValueError(f"{path}: no valid 'part' entry") from None
        if path.name != part_manifest_name(*key):
            raise ValueError(f"{path}: holds part {key[0]}/{key[1]} (renamed?)")
        for name in man["shards"]:
            if name in owner:
                raise ValueError(f"{path}: claims {name}, which {owner[name].name} claims too "
                                 "(a part run twice, with another N); remove the part manifest that is not wanted")
            owner[name] = path
        parts[key] = (path, man)
    ns = sorted({n for _, n in parts})
    if len(ns) > 1:
        a = next(p for (i, n), (p, _) in parts.items() if n == ns[0])
        b = next(p for (i, n), (p, _) in parts.items() if n == ns[1])
        raise ValueError(f"{b}: a part of {ns[1]}, but {a.name} is a part of {ns[0]}; one partition per dataset")
    n = ns[0]
    for i in range(1, n + 1):
        if (i, n) not in parts:
            raise ValueError(f"{out / part_manifest_name(i, n)}: missing (part {i}/{n} has not run here)")
    path0, man0 = parts[(1, n)]
    writer = ShardWriter(out, int(man0.get("num_samples", 0)), int(man0.get("shard_size", 0)), int(man0.get("seed", 0)),
                         config=man0.get("config", {}), versions=man0.get("versions", {}), tag=tag)
    shards: dict[str, Any] = {}
    skipped: list[dict[str, Any]] = []
    for (i, _), (path, man) in sorted(parts.items()):
        writer.same_run(man, path, f"not a part of the run of {path0.name}")
        if man.get("versions") != man0.get("versions"):
            raise ValueError(f"{path}: made with other package versions than {path0.name}")
        part = ShardWriter(out, writer.num, writer.shard_size, writer.seed, part=(i, n))
        want = {shard_name(x) for x in part.shards()}
        if set(man["shards"]) != want or not man.get("complete"):
            raise ValueError(f"{path}: part {i}/{n} is unfinished ({len(man['shards'])} of {len(want)} shards); "
                             f"continue it with --part {i}/{n} --resume")
        for name, entry in man["shards"].items():
            p = out / name
            if not p.is_file():
                raise ValueError(f"{p}: missing (listed in {path.name})")
            if sha256_file(p) != entry.get("sha256"):
                raise ValueError(f"{p}: SHA-256 differs from {path.name} (damaged, or written by another run)")
            shards[name] = entry
        skipped += man.get("skipped", [])
    merged = writer.write_manifest(shards, skipped)
    for path, _ in parts.values():
        path.unlink()
    return merged
