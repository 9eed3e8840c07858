"""One writer per output folder (or per part of it): lock files naming their holder.

Design:

- A writer of the whole dataset holds ``DIR/.lock``; a writer of part ``I`` of ``N`` (the coming
  ``--part I/N`` runs, each making a disjoint set of shards in one folder at the same time) holds
  ``DIR/.lock-part-I-of-N``. Two parts of the same ``N`` never conflict; any other pair of locks
  does (the whole dataset overlaps every part, and parts of different ``N`` overlap each other).
- A lock file holds JSON naming its holder: ``host``, ``pid``, ``started`` (UTC, ISO 8601),
  ``part``, ``parts``. Mutual exclusion is an exclusive ``flock`` on the file, held as long as the
  writer runs: the kernel drops it when the process dies, however it dies (even ``kill -9``), so a
  live writer is never taken over and a dead one never blocks a new run for long.
- A second writer is refused with one line naming the holder. A lock file whose ``flock`` is free
  was left by a dead process: on the same host it is taken over with a warning (and the temporary
  files carrying the dead writer's tag are removed); from another host it is refused, since its
  process cannot be checked from here (flock over NFS is not always shared between hosts).
  Where the file system has no ``flock`` (``ENOLCK``), the holder's pid decides on the same host.
- After taking its own file, a writer looks at every other lock file of the folder and is refused
  if a conflicting one is held. Two conflicting writers starting at the same instant may then both
  be refused, never both admitted.
- Temporary files carry the writer's :attr:`OutputLock.tag` (``<host>.<pid>``), so that two writers
  never write the same temporary file.
- Work the parts of one run share (the dataset's subjects) is done under :func:`exclusive`
  (``DIR/.lock-subjects``, a blocking ``flock``): the first part makes the subjects, the others
  wait for it and reuse them.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import fcntl
import json
import os
import re
import socket
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

LOCK_PREFIX = ".lock"
_PART = re.compile(r"^\.lock(?:-part-(\d+)-of-(\d+))?$")


def lock_name(part: int = 1, parts: int = 1) -> str:
    """``.lock`` for the whole dataset, ``.lock-part-I-of-N`` for part ``I`` (1-based) of ``N``."""
    if not 1 <= part <= parts:
        raise ValueError(f"part must be in [1, {parts}], got {part}")
    return LOCK_PREFIX if parts == 1 else f"{LOCK_PREFIX}-part-{part}-of-{parts}"


def conflicts(a: tuple[int, int], b: tuple[int, int]) -> bool:
    """Whether writers of parts ``a`` and ``b`` (``(I, N)``; ``(1, 1)`` is the whole) can overlap."""
    return a[1] != b[1] or a[0] == b[0] or a[1] == 1


def _host() -> str:
    return socket.gethostname() or "localhost"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except (OSError, OverflowError, ValueError):
        return False
    return True


def describe(holder: dict[str, Any]) -> str:
    """The holder of a lock in words: ``host H, pid P, since T``."""
    return f"host {holder.get('host', '?')}, pid {holder.get('pid', '?')}, since {holder.get('started', '?')}"


def _read(fd: int) -> dict[str, Any]:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        data = json.loads(os.read(fd, 1 << 16).decode("utf-8") or "{}")
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _try_flock(fd: int) -> bool | None:
    """True when this fd now holds the flock, False when another does, None when unsupported."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    except OSError as exc:
        if exc.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
            return None
        raise
    return True


@dataclass
class OutputLock:
    """A held lock; :meth:`release` (or leaving the ``with`` block) gives it back."""

    path: Path
    fd: int
    holder: dict[str, Any]

    @property
    def tag(self) -> str:
        """``<host>.<pid>``, safe in a file name: the writer's mark on its temporary files."""
        return tag_of(self.holder)

    def release(self) -> None:
        if self.fd < 0:
            return
        with contextlib.suppress(OSError):
            # Unlinked while still held, so no one can take the file between the two steps.
            if os.path.samestat(os.fstat(self.fd), os.stat(self.path)):
                self.path.unlink()
        os.close(self.fd)
        self.fd = -1

    def __enter__(self) -> OutputLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def tag_of(holder: dict[str, Any]) -> str:
    host = re.sub(r"[^A-Za-z0-9_-]", "_", str(holder.get("host", "")))
    return f"{host}.{holder.get('pid', '')}"


def acquire(
    folder: str | Path,
    part: int = 1,
    parts: int = 1,
    warn: Callable[[str], None] | None = None,
    stale_files: Callable[[str], list[Path]] | None = None,
) -> OutputLock:
    """Take the lock of ``folder`` (part ``part`` of ``parts``); the folder must exist.

    Args:
        warn: called with a one-line warning when a dead writer's lock is taken over.
        stale_files: ``tag -> files`` left by a dead writer with that tag; they are removed when
            its lock is taken over.

    Raises:
        ValueError: one line naming the folder and the holder when a conflicting writer runs.
    """
    folder = Path(folder)
    path = folder / lock_name(part, parts)
    me = {
        "host": _host(),
        "pid": os.getpid(),
        "started": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "part": part,
        "parts": parts,
    }
    for _ in range(10):
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        got = _try_flock(fd)
        if got is False:
            holder = _read(fd)
            os.close(fd)
            raise ValueError(f"{folder}: in use by another synth generate ({describe(holder)}; lock {path.name})")
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if not same:  # released and unlinked between our open and flock: start again
            os.close(fd)
            continue
        break
    else:  # pragma: no cover - ten releases in a row while we try
        raise ValueError(f"{folder}: cannot take the lock {path.name} (it keeps changing)")
    old = _read(fd)
    if old:
        if old.get("host") != me["host"]:
            os.close(fd)
            raise ValueError(
                f"{folder}: locked by a run on another host ({describe(old)}); "
                f"if that run is gone, remove {path}"
            )
        if got is None and _alive(int(old.get("pid", -1))) and old.get("pid") != me["pid"]:
            os.close(fd)
            raise ValueError(f"{folder}: in use by another synth generate ({describe(old)}; lock {path.name})")
        if warn is not None:
            warn(f"{path}: taking over the lock of a run that is gone ({describe(old)})")
        if stale_files is not None:
            for f in stale_files(tag_of(old)):
                f.unlink(missing_ok=True)
    os.ftruncate(fd, 0)
    os.lseek(fd, 0, os.SEEK_SET)
    os.write(fd, (json.dumps(me, sort_keys=True) + "\n").encode())
    os.fsync(fd)
    lock = OutputLock(path, fd, me)
    try:
        _check_others(folder, path, (part, parts))
    except BaseException:
        lock.release()
        raise
    return lock


def _check_others(folder: Path, mine: Path, part: tuple[int, int]) -> None:
    for other in sorted(folder.glob(f"{LOCK_PREFIX}*")):
        m = _PART.match(other.name)
        if other == mine or m is None:
            continue
        theirs = (int(m.group(1) or 1), int(m.group(2) or 1))
        if not conflicts(part, theirs):
            continue
        try:
            fd = os.open(other, os.O_RDONLY)
        except FileNotFoundError:
            continue
        try:
            if _try_flock(fd) is False:
                raise ValueError(
                    f"{folder}: in use by another synth generate ({describe(_read(fd))}; lock {other.name})"
                )
        finally:
            os.close(fd)  # also drops the flock when we got it (the file stays, a dead one's)


@contextlib.contextmanager
def exclusive(path: str | Path, waiting: Callable[[], None] | None = None) -> Iterator[None]:
    """Hold the blocking ``flock`` of ``path`` (created if missing) for the ``with`` block.

    For work that concurrent writers of one folder must do once (the parts of a run making the
    dataset's subjects): the first does it, the others wait and then find it done. ``waiting`` is
    called once if another process holds the lock. The file is left in place (unlinking a lock file
    others may be waiting on would let two holders in).
    """
    path = Path(path)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        got = _try_flock(fd)
        if got is False:
            if waiting is not None:
                waiting()
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # drops the flock
