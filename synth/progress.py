"""What a run tells its user: ``[synth]`` lines on stderr, and the progress meter."""

from __future__ import annotations

import math
import sys
import time
from typing import Any


def log(msg: str) -> None:
    """One ``[synth]`` line on stderr."""
    print(f"[synth] {msg}", file=sys.stderr, flush=True)


def hms(s: float) -> str:
    """Seconds as ``1h02m`` or ``3m04s`` (``--`` when not finite)."""
    if not math.isfinite(s):
        return "--"
    s = int(s)
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


class Progress:
    """Images done, rate and ETA on stderr: one updating line on a terminal, a line every 30 s
    (and one per shard) otherwise."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.total, self.enabled, self.made = total, enabled, 0
        self.t0 = self.last = time.time()
        self.tty = sys.stderr.isatty()

    def elapsed(self) -> float:
        return time.time() - self.t0

    def line(self) -> str:
        rate = self.made / max(self.elapsed(), 1e-9)
        eta = (self.total - self.made) / rate if rate > 0 else float("nan")
        pct = 100.0 * self.made / max(self.total, 1)
        return f"{self.made}/{self.total} images ({pct:.0f} %)  {rate:.2f} img/s  ETA {hms(eta)}"

    def tick(self) -> None:
        self.made += 1
        if not self.enabled:
            return
        if self.tty:
            print(f"\r[synth] {self.line()}   ", end="", file=sys.stderr, flush=True)
        elif time.time() - self.last >= 30:
            self.last = time.time()
            log(self.line())

    def shard(self, msg: str) -> None:
        if self.enabled and not self.tty:
            log(f"{msg}; {self.line()}")

    def close(self) -> None:
        if self.enabled and self.tty:
            print(file=sys.stderr, flush=True)

    def done(self, man: dict[str, Any]) -> None:
        """The run's last line: samples, shards, time and skipped samples of manifest ``man``."""
        n, lost = sum(e["samples"] for e in man["shards"].values()), len(man["skipped"])
        log(f"done: {n} samples in {len(man['shards'])} shards, {hms(self.elapsed())}" + (f", {lost} skipped" if lost else ""))
