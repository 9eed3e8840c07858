"""The samples of a dataset folder: ``manifest.json`` and the shards' tar headers read into byte
ranges (:class:`DatasetIndex`), and the PNG check every reader runs before decoding."""

from __future__ import annotations

import os
import tarfile
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any, BinaryIO

from blsm.io import sha256_file
from synth.dataset import format as fmt
from synth.dataset.shards import FORMAT as SHARDS_FORMAT
from synth.dataset.shards import MANIFEST

__all__ = ["IMAGE_FIELDS", "DatasetIndex", "check_png_crc"]

IMAGE_FIELDS = ("json", "rgb.png", "mask.png", "parts.png")
"""The members every sample of an image dataset has."""


class DatasetIndex:
    """The samples of a dataset folder and the byte ranges of their tar members.

    Built from ``manifest.json`` and the shards' tar headers; :meth:`read` then reads one member with
    one seek. File handles are opened lazily per process, so the index survives ``fork`` (DataLoader
    workers) and pickling.

    Raises:
        ValueError: one line naming the file, on a missing folder or manifest, a manifest of another
            format, an incomplete run (unless ``allow_incomplete``), a missing or truncated shard, a
            shard whose SHA-256 differs from the manifest's (with ``verify``; it reads every byte), or
            a sample without the ``required`` members.
    """

    def __init__(self, path: str | Path, allow_incomplete: bool = False, required: Sequence[str] = IMAGE_FIELDS,
                 verify: bool = False):
        self.root, self.required = Path(path), tuple(required)
        man_path = self.root / MANIFEST
        if not man_path.is_file():
            raise ValueError(f"{man_path}: no dataset manifest here")
        try:
            man = fmt.decode_json(man_path.read_bytes(), str(man_path))
        except OSError as exc:
            raise ValueError(f"{man_path}: unreadable ({exc.strerror})") from None
        if not isinstance(man, dict) or man.get("format") != SHARDS_FORMAT:
            raise ValueError(f"{man_path}: not a {SHARDS_FORMAT!r} manifest")
        if not man.get("complete") and not allow_incomplete:
            raise ValueError(f"{man_path}: the dataset is incomplete (generation unfinished)")
        self.config: dict[str, Any] = man.get("config") if isinstance(man.get("config"), dict) else {}
        shards = man.get("shards") or {}
        if not isinstance(shards, dict) or not all(
            isinstance(e, dict) and isinstance(e.get("samples", -1), int) for e in shards.values()
        ):
            raise ValueError(f"{man_path}: 'shards' must map each shard's name to its entry")
        self.shards: list[Path] = []
        self.samples: list[tuple[int, str, dict[str, tuple[int, int]]]] = []
        for name, entry in sorted(shards.items()):
            path = self.root / name
            if verify and path.is_file() and sha256_file(path) != entry.get("sha256"):
                raise ValueError(f"{path}: SHA-256 differs from the manifest (damaged or edited)")
            self._index_shard(len(self.shards), path, int(entry.get("samples", -1)))
        self._pid = -1
        self._files: dict[int, BinaryIO] = {}

    def _index_shard(self, s: int, path: Path, expected: int) -> None:
        if not path.is_file():
            raise ValueError(f"{path}: shard listed in the manifest is missing")
        size = path.stat().st_size
        members: dict[str, dict[str, tuple[int, int]]] = {}
        try:
            with tarfile.open(path, mode="r:") as tar:
                for m in tar:
                    if m.isfile():
                        if m.offset_data + m.size > size:
                            raise ValueError(f"{path}: truncated shard (member {m.name} ends past the file)")
                        key, _, name = m.name.partition(".")
                        members.setdefault(key, {})[name] = (m.offset_data, m.size)
        except (OSError, tarfile.TarError) as exc:
            raise ValueError(f"{path}: not a readable shard ({exc})") from None
        if expected >= 0 and len(members) != expected:
            raise ValueError(f"{path}: holds {len(members)} samples, the manifest says {expected}")
        for key, fields in members.items():
            missing = [f for f in self.required if f not in fields]
            if missing:
                raise ValueError(f"{path}: sample {key} lacks {missing} (truncated or not a synth dataset)")
        self.shards.append(path)
        self.samples.extend((s, key, fields) for key, fields in members.items())

    def __len__(self) -> int:
        return len(self.samples)

    def where(self, i: int) -> str:
        s, key, _ = self.samples[i]
        return f"{self.shards[s]}:{key}"

    def read(self, i: int, fields: Sequence[str]) -> dict[str, bytes]:
        """The raw bytes of the given members of sample ``i`` (a ValueError names a missing one)."""
        if os.getpid() != self._pid:  # a forked worker must not share the parent's file offsets
            self._files, self._pid = {}, os.getpid()
        s, key, members = self.samples[i]
        fh = self._files.get(s)
        if fh is None:
            fh = self._files[s] = open(self.shards[s], "rb")  # kept open: one per shard per process
        out = {}
        for name in fields:
            if name not in members:
                raise ValueError(f"{self.where(i)}: sample has no {name!r} member")
            offset, size = members[name]
            fh.seek(offset)
            out[name] = fh.read(size)
            if len(out[name]) != size:
                raise ValueError(f"{self.where(i)}.{name}: truncated member")
        return out

    def json(self, i: int) -> dict[str, Any]:
        return fmt.decode_json(self.read(i, ("json",))["json"], f"{self.where(i)}.json")

    def close(self) -> None:
        """Close this process's open shard files (they reopen on the next read)."""
        if self._pid == os.getpid():
            for fh in self._files.values():
                fh.close()
        self._files = {}

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_files": {}, "_pid": -1}


def check_png_crc(data: bytes, what: str) -> None:
    """Check the CRC of every chunk of PNG bytes (a ValueError naming ``what`` on a mismatch).

    PIL does not check the image data's CRCs and stops inflating once it has every row, so a
    damaged byte there can decode, silently, into wrong pixels.
    """
    if not data.startswith(b"\x89PNG\r\n\x1a\n"):
        return  # not a PNG at all: decoding says so
    pos = 8
    while pos + 12 <= len(data):
        n = int.from_bytes(data[pos : pos + 4], "big")
        body, crc = data[pos + 4 : pos + 8 + n], data[pos + 8 + n : pos + 12 + n]
        if len(crc) < 4 or zlib.crc32(body).to_bytes(4, "big") != crc:
            chunk = body[:4].decode("latin-1")
            raise ValueError(f"{what}: not a readable PNG (bad CRC in its {chunk!r} chunk)")
        pos += 12 + n
