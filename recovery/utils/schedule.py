"""Learning-rate schedules shared by the training tasks."""

from __future__ import annotations

import math


def warmup_cosine(step: int, total: int, warmup: int, schedule: str) -> float:
    """Learning-rate factor: linear warm-up over ``warmup`` steps, then constant or cosine to 0."""
    if warmup and step < warmup:
        return (step + 1) / warmup
    if schedule == "constant":
        return 1.0
    t = (step - warmup) / max(total - warmup, 1)
    return 0.5 * (1.0 + math.cos(math.pi * min(max(t, 0.0), 1.0)))
