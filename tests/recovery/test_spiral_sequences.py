"""blsm.spiral.sequences: Eq. 4.3's spirals."""

from __future__ import annotations

import numpy as np
import pytest
from recovery_helpers import sphere

from blsm.spiral.sequences import spiral_sequences, vertex_fans


def grid(n: int = 5, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """An open n x n grid in the z = 0 plane, wound counterclockwise seen from +z."""
    rng = np.random.default_rng(seed)
    xy = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="xy"), -1).reshape(-1, 2).astype(float)
    v = np.concatenate([xy + 0.1 * rng.random(xy.shape), np.zeros((len(xy), 1))], 1)
    f = []
    for r in range(n - 1):
        for c in range(n - 1):
            a, b, d, e = r * n + c, r * n + c + 1, (r + 1) * n + c, (r + 1) * n + c + 1
            f += [[a, b, e], [a, e, d]]
    return v, np.asarray(f)


def directed_edges(faces: np.ndarray) -> set[tuple[int, int, int]]:
    """(x, a, b) for every face and rotation: going around x counterclockwise, a then b."""
    out = set()
    for a, b, c in faces.tolist():
        out |= {(a, b, c), (b, c, a), (c, a, b)}
    return out


def rings(faces: np.ndarray, nv: int, x: int, h: int) -> list[set[int]]:
    nb = [set() for _ in range(nv)]
    for a, b, c in faces.tolist():
        nb[a] |= {b, c}
        nb[b] |= {a, c}
        nb[c] |= {a, b}
    seen, ring, out = {x}, {x}, []
    for _ in range(h):
        ring = set().union(*(nb[u] for u in ring)) - seen
        seen |= ring
        out.append(ring)
    return out


def test_spiral_order_on_a_closed_mesh():
    v, f = sphere()
    s = spiral_sequences(v, f, rings=2, length=40)
    tri = directed_edges(f)
    for x in range(len(v)):
        r1, r2 = rings(f, len(v), x, 2)
        seq = s[x][s[x] >= 0].tolist()
        assert seq[0] == x
        first = seq[1: 1 + len(r1)]
        assert set(first) == r1 and set(seq[1 + len(r1):]) == r2
        # R^1_1 is the closest neighbour
        assert first[0] == min(r1, key=lambda u: np.linalg.norm(v[u] - v[x]))
        # counterclockwise seen from outside: consecutive ring elements span a face (x, a, b)
        for a, b in zip(first, first[1:] + first[:1]):
            assert (x, a, b) in tri


def test_spiral_length_truncates_and_pads():
    v, f = sphere(1)
    long = spiral_sequences(v, f, rings=2, length=40)
    short = spiral_sequences(v, f, rings=2, length=7)
    assert short.shape == (len(v), 7)
    np.testing.assert_array_equal(short, long[:, :7])
    n2 = (long >= 0).sum(1)
    assert (n2 < 40).all()
    for x in range(len(v)):
        assert (long[x, n2[x]:] == -1).all()  # padding only at the end
    one = spiral_sequences(v, f, rings=1, length=40)
    np.testing.assert_array_equal((one >= 0).sum(1), 1 + np.array([len(r[0]) for r in (rings(f, len(v), x, 1) for x in range(len(v)))]))


def test_spiral_on_an_open_mesh_keeps_every_neighbour():
    v, f = grid()
    fans, closed = vertex_fans(f, len(v))
    assert not closed[0] and closed[12]  # a corner, the centre
    s = spiral_sequences(v, f, rings=2, length=30)
    for x in range(len(v)):
        r1, r2 = rings(f, len(v), x, 2)
        got = set(s[x][s[x] >= 0].tolist())
        assert got == {x} | r1 | r2


def test_spirals_follow_a_relabelling():
    v, f = sphere()
    perm = np.random.default_rng(3).permutation(len(v))  # new vertex i is old vertex perm[i]
    inv = np.argsort(perm)
    s = spiral_sequences(v, f, rings=2, length=19)
    s2 = spiral_sequences(v[perm], inv[f], rings=2, length=19)
    mapped = np.where(s[perm] >= 0, inv[np.maximum(s[perm], 0)], -1)
    np.testing.assert_array_equal(s2, mapped)


def test_bad_spiral_arguments():
    v, f = sphere(0)
    with pytest.raises(ValueError, match="rings and length"):
        spiral_sequences(v, f, rings=0, length=5)
