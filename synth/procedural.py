"""Procedural primitives shared by the painters of :mod:`synth.textures` and
:mod:`synth.skin_detail` and by the cloth folds of :mod:`synth.garments`: value noise and the skin
palette (a module of their own, so that those modules import it and not each other)."""

from __future__ import annotations

import numpy as np

# Linear RGB skin albedos from very light to very dark.
SKIN_PALETTE = np.array([
    [0.62, 0.45, 0.36], [0.55, 0.38, 0.29], [0.47, 0.31, 0.22], [0.38, 0.24, 0.16],
    [0.29, 0.17, 0.11], [0.21, 0.12, 0.075], [0.14, 0.08, 0.05], [0.09, 0.05, 0.035],
])  # fmt: skip


def value_noise(p: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Trilinear value noise in [0, 1] of points p (N, 3) on the unit lattice."""
    i = np.floor(p)
    f = p - i
    f = f * f * (3 - 2 * f)
    i = i.astype(np.int64)
    hashes = [(i[:, a] * k, (i[:, a] + 1) * k) for a, k in enumerate((73856093, 19349663, 83492791))]
    weights = [(1 - f[:, a], f[:, a]) for a in range(3)]
    out = np.zeros(len(p))
    for cx, cy, cz in np.ndindex(2, 2, 2):
        h = (hashes[0][cx] ^ hashes[1][cy] ^ hashes[2][cz]) & (len(table) - 1)
        out += weights[0][cx] * weights[1][cy] * weights[2][cz] * table[h]
    return out
