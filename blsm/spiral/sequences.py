"""Spiral sequences (thesis Eq. 4.3, Sec. 4.3.1; Lim et al. 2018, Neural3DMM), precomputed on a template.

For a vertex ``x`` the spiral is ``S(x) = x, R^1_1(x), R^1_2(x), ..., R^h_{|R^h|}(x)``: ``x``, then
its 1-ring, 2-ring, ... up to ring ``h`` (the kernel size of Table 4.1). The first element of the
1-ring is the **closest** neighbour of ``x`` (Euclidean, on the template's positions) and every ring
is walked **counterclockwise** seen from outside the surface (the faces' winding; a closed template
must be wound outward). Ring ``d + 1`` continues the spiral outward: for each vertex ``u`` of ring
``d`` in order, the not yet visited neighbours of ``u`` are appended in ``u``'s counterclockwise fan
order, starting after the part of the fan that lies inside the disk of rings ``<= d``. Nothing in the
construction depends on vertex indices (only on the closest neighbour and the winding), so a
consistent relabelling of the template relabels the spirals.

Every spiral is truncated or padded to a fixed ``length`` per level (spiralnet++ truncates; padding
uses ``-1``, which :class:`blsm.spiral.conv.SpiralConv` reads as a zero feature).
"""

from __future__ import annotations

import numpy as np


def vertex_fans(faces: np.ndarray, num_vertices: int) -> tuple[list[list[int]], list[bool]]:
    """Each vertex's neighbours in counterclockwise order around it (the face winding).

    Args:
        faces: (F, 3) triangles, wound counterclockwise seen from outside.
        num_vertices: V.

    Returns:
        V lists and V flags "closed". A closed fan is a cycle (its start is arbitrary); at a
        boundary vertex the fan is open and starts at the boundary edge with no predecessor.
    """
    nxt: list[dict[int, int]] = [dict() for _ in range(num_vertices)]
    for a, b, c in np.asarray(faces, dtype=np.int64).tolist():
        # in a counterclockwise triangle (a, b, c), going around a: b then c; around b: c then a; ...
        nxt[a][b] = c
        nxt[b][c] = a
        nxt[c][a] = b
    fans: list[list[int]] = []
    closed: list[bool] = []
    for v in range(num_vertices):
        m = nxt[v]
        if not m:
            fans.append([])
            closed.append(False)
            continue
        targets = set(m.values())
        starts = sorted(k for k in m if k not in targets)  # boundary: the fan's open end
        start = starts[0] if starts else min(m)  # a cycle: any start (rotated later by geometry)
        fan, cur, seen = [start], start, {start}
        while cur in m and m[cur] not in seen:
            cur = m[cur]
            fan.append(cur)
            seen.add(cur)
        for k in sorted(set(m) | targets):  # a non-manifold vertex: keep every neighbour once
            if k not in seen:
                fan.append(k)
                seen.add(k)
        fans.append(fan)
        closed.append(not starts and len(fan) == len(m))
    return fans, closed


def _rotate_after_inside(fan: list[int], inside: set[int]) -> list[int]:
    """``fan`` rotated to start just after its last run of ``inside`` vertices (cyclic), so the
    outside vertices come as one counterclockwise arc."""
    n = len(fan)
    for i in range(n):
        if fan[i] in inside and fan[(i + 1) % n] not in inside:
            return fan[i + 1:] + fan[: i + 1]
    return fan


def spiral_sequences(positions: np.ndarray, faces: np.ndarray, rings: int, length: int) -> np.ndarray:
    """The spiral of every vertex (module docstring).

    Args:
        positions: (V, 3) template positions (pick the closest neighbour).
        faces: (F, 3) counterclockwise triangles.
        rings: h >= 1, the number of rings (Table 4.1's kernel size).
        length: L, the fixed spiral length (truncated or padded with -1).

    Returns:
        (V, L) int64 vertex indices; column 0 is the vertex itself.
    """
    if rings < 1 or length < 1:
        raise ValueError(f"rings and length must be >= 1, got {rings}, {length}")
    positions = np.asarray(positions, dtype=np.float64)
    nv = len(positions)
    fans, closed = vertex_fans(faces, nv)
    out = np.full((nv, length), -1, dtype=np.int64)
    for x in range(nv):
        fan = fans[x]
        seq = [x]
        if fan:
            d = np.linalg.norm(positions[fan] - positions[x], axis=1)
            i0 = int(np.argmin(d))
            ring = fan[i0:] + fan[:i0] if closed[x] else fan  # an open fan keeps its boundary order
            inside = {x}
            for _ in range(rings):
                ring = [u for u in ring if u not in inside]
                if not ring:
                    break
                seq += ring
                inside.update(ring)
                if len(seq) >= length:
                    break
                nxt_ring: list[int] = []
                seen = set(inside)
                for u in ring:
                    for w in _rotate_after_inside(fans[u], inside) if closed[u] else fans[u]:
                        if w not in seen:
                            nxt_ring.append(w)
                            seen.add(w)
                ring = nxt_ring
        seq = seq[:length]
        out[x, : len(seq)] = seq
    return out
