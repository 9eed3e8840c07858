"""Colours and props for the Anny stand-in scans: a textured look, a stool, markers on the floor.

Real scans (photogrammetry, 4D capture rigs; thesis Sec. 6.2) come with a texture and often with
things that are not the person: a chair or a stool, markers on the floor, a step (thesis Sec. 6.3.1).
:mod:`blsm.learn.scans.population` uses these functions so that markerless registration
(:mod:`blsm.learn.markerless.keypoints`) has something to look at and something to ignore.

* :func:`paint_body`: per-vertex sRGB colours on Anny's topology: a skin tone from the subject's
  ethnic mix, a top (torso, with short or long sleeves), trousers or shorts, shoes, hair on the
  back and top of the head, and a little per-vertex noise. Colours are a function of the rest body
  and the random generator only, so every pose of a subject wears the same clothes. Simple on
  purpose (no UV texture, no folds): enough for a 2D pose detector to see a clothed person.
* :func:`stool_mesh`: a closed cylinder (a stool seat on the floor, 0.45 m high by default) beside
  the body, placed at the first distance where it does not touch the legs.
* :func:`floor_markers`: small flat discs (2.5 cm radius, 3 mm thick) on the floor around the body.

Lengths in metres, world frame Y up, colours (N, 3) uint8 sRGB.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

Mesh3 = tuple[np.ndarray, np.ndarray, np.ndarray]
"""A coloured mesh: vertices (N, 3) float, faces (F, 3) int, colours (N, 3) uint8."""

SKIN_TONES: dict[str, tuple[float, float, float]] = {
    "african": (0.38, 0.25, 0.18),
    "asian": (0.86, 0.70, 0.56),
    "caucasian": (0.93, 0.77, 0.67),
}
"""sRGB base skin tone per Anny ethnicity weight (the subject's tone is the weighted mix)."""

CLOTH_PALETTE: tuple[tuple[float, float, float], ...] = (
    (0.15, 0.22, 0.45), (0.55, 0.10, 0.12), (0.20, 0.40, 0.22), (0.85, 0.85, 0.82), (0.12, 0.12, 0.13),
    (0.60, 0.55, 0.45), (0.35, 0.35, 0.40), (0.80, 0.55, 0.15), (0.45, 0.30, 0.55), (0.30, 0.55, 0.70),
)
"""sRGB garment colours (tops, trousers, shoes and hair are drawn from it or near it)."""

HAIR_COLORS: tuple[tuple[float, float, float], ...] = (
    (0.08, 0.06, 0.05), (0.25, 0.16, 0.09), (0.55, 0.40, 0.22), (0.75, 0.62, 0.40), (0.45, 0.45, 0.45),
)

_TOP = ("spine", "clavicle", "shoulder01", "root")
_SLEEVE_SHORT = ("upperarm01",)
_SLEEVE_LONG = ("upperarm01", "upperarm02", "lowerarm01")
_SHORTS = ("pelvis", "upperleg01")
_TROUSERS = ("pelvis", "upperleg01", "upperleg02", "lowerleg01", "lowerleg02")
_SHOES = ("foot", "toe")


def _bones(labels: Sequence[str], prefixes: Sequence[str]) -> np.ndarray:
    return np.array([i for i, lab in enumerate(labels) if lab.startswith(tuple(prefixes))], dtype=np.int64)


def paint_body(
    rest: np.ndarray,
    weights: np.ndarray,
    labels: Sequence[str],
    phenotype: dict[str, float],
    rng: np.random.Generator,
) -> np.ndarray:
    """Per-vertex colours of one Anny body (skin, clothing-like regions by body part, hair).

    Args:
        rest: (Va, 3) rest vertices, metres (world frame, facing +Z).
        weights: (Va, Ka) Anny skinning weights (a vertex belongs to its dominant bone).
        labels: Ka Anny bone labels.
        phenotype: Anny phenotype; ``african``, ``asian``, ``caucasian`` mix the skin tone.
        rng: the subject's generator (draws garment kinds and colours, then the noise).

    Returns:
        (Va, 3) uint8 sRGB colours.
    """
    mix = np.array([phenotype.get(k, 1.0 / 3.0) for k in SKIN_TONES])
    mix = mix / max(mix.sum(), 1e-9)
    skin = mix @ np.array(list(SKIN_TONES.values())) * rng.uniform(0.92, 1.05)
    dominant = weights.argmax(1)
    out = np.tile(skin, (len(rest), 1))
    palette = np.array(CLOTH_PALETTE)
    top_c, bottom_c, shoe_c = palette[rng.choice(len(palette), 3, replace=False)]
    sleeves = _SLEEVE_LONG if rng.random() < 0.5 else _SLEEVE_SHORT
    legs = _TROUSERS if rng.random() < 0.6 else _SHORTS
    for prefixes, colour in ((_TOP + sleeves, top_c), (legs, bottom_c), (_SHOES, shoe_c)):
        out[np.isin(dominant, _bones(labels, prefixes))] = colour
    # Hair: the head's vertices near its top, and further down at the back of the head.
    head = np.isin(dominant, _bones(labels, ("head",)))
    if head.any():
        top = rest[head, 1].max()
        size = top - rest[head, 1].min()
        back = rest[:, 2] < np.median(rest[head, 2]) - 0.1 * size
        hair = head & ((rest[:, 1] > top - 0.22 * size) | (back & (rest[:, 1] > top - 0.6 * size)))
        out[hair] = np.array(HAIR_COLORS[int(rng.integers(len(HAIR_COLORS)))])
    out = out * rng.normal(1.0, 0.04, size=(len(out), 1))  # a little shading noise per vertex
    return np.round(np.clip(out, 0.0, 1.0) * 255.0).astype(np.uint8)


def _cylinder(radius: float, height: float, sections: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed cylinder along +Y, centred at the origin: (V, 3), (F, 3), outward normals."""
    import trimesh

    cyl = trimesh.creation.cylinder(radius=radius, height=height, sections=sections)
    v = np.asarray(cyl.vertices)[:, [0, 2, 1]] * np.array([1.0, 1.0, -1.0])  # z-axis -> y-axis, proper
    return v, np.asarray(cyl.faces, dtype=np.int64)


def _centre_xz(body: np.ndarray) -> np.ndarray:
    return 0.5 * (body[:, [0, 2]].min(0) + body[:, [0, 2]].max(0))


def stool_mesh(
    body: np.ndarray, floor_y: float, rng: np.random.Generator, radius: float = 0.17, height: float = 0.45
) -> Mesh3:
    """A stool (a closed cylinder standing on the floor) beside the body, not touching it.

    A random direction about +Y from the body's centre (its box in x, z); the distance grows by
    2 cm from 0.15 m until the cylinder keeps 3 cm from every body vertex below its top + 5 cm.

    Args:
        body: (N, 3) the body's vertices, metres.
        floor_y: the floor's height, metres.
        rng: draws the direction.
        radius, height: the stool's, metres.

    Returns:
        (vertices (V, 3), faces (F, 3), colours (V, 3) uint8): a wooden brown.
    """
    v, f = _cylinder(radius, height, 32)
    a = rng.uniform(0.0, 2.0 * np.pi)
    direction = np.array([np.cos(a), np.sin(a)])
    low = body[body[:, 1] < floor_y + height + 0.05][:, [0, 2]]
    centre = _centre_xz(body)
    d = 0.15
    while low.size and np.linalg.norm(low - (centre + d * direction), axis=1).min() < radius + 0.03:
        d += 0.02
    cx, cz = centre + d * direction
    v = v + np.array([cx, floor_y + height / 2.0, cz])
    colour = np.array([0.48, 0.32, 0.18]) * rng.normal(1.0, 0.03, size=(len(v), 1))
    return v, f, np.round(np.clip(colour, 0, 1) * 255).astype(np.uint8)


def floor_markers(
    body: np.ndarray, floor_y: float, n: int, rng: np.random.Generator, radius: float = 0.025
) -> Mesh3:
    """``n`` flat discs (``radius``, 3 mm thick) on the floor, 0.3-0.7 m from the body's centre.

    A disc that would lie under the body (a body vertex within 5 cm above the floor and 3 cm of the
    disc's edge, horizontally) is drawn again (at most 50 tries, then kept). Colours alternate
    black and a bright yellow, like tape markers.

    Returns:
        (vertices (V, 3), faces (F, 3), colours (V, 3) uint8); empty arrays for ``n = 0``.
    """
    if n <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.uint8)
    disc_v, disc_f = _cylinder(radius, 0.003, 16)
    feet = body[body[:, 1] < floor_y + 0.05][:, [0, 2]]
    centre = _centre_xz(body)
    parts = []
    for i in range(n):
        for _ in range(50):
            a, r = rng.uniform(0.0, 2.0 * np.pi), rng.uniform(0.3, 0.7)
            c = centre + r * np.array([np.cos(a), np.sin(a)])
            if not feet.size or np.linalg.norm(feet - c, axis=1).min() > radius + 0.03:
                break
        colour = (20, 20, 20) if i % 2 else (240, 200, 30)
        parts.append((disc_v + np.array([c[0], floor_y + 0.0015, c[1]]), disc_f,
                      np.tile(np.array(colour, np.uint8), (len(disc_v), 1))))
    return merge_meshes(parts)


def merge_meshes(parts: Sequence[Mesh3]) -> Mesh3:
    """One coloured mesh from several (faces re-indexed; the parts stay separate components)."""
    verts, faces, cols, n = [], [], [], 0
    for v, f, c in parts:
        verts.append(np.asarray(v, np.float64))
        faces.append(np.asarray(f, np.int64) + n)
        cols.append(np.asarray(c, np.uint8))
        n += len(v)
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(cols)


def add_props(
    v: np.ndarray, f: np.ndarray, colors: np.ndarray, body: np.ndarray, stool: bool, markers: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, list[int]]]:
    """A scan mesh with a stool and ``markers`` floor markers appended (floor = the body's lowest y).

    Args:
        v, f, colors: the scan's (N, 3) vertices, (F, 3) faces, (N, 3) uint8 colours.
        body: (Nb, 3) the clean body's vertices (placement and the floor height), metres.
        stool: add a stool (:func:`stool_mesh`); markers: number of discs (:func:`floor_markers`).
        rng: draws the stool's, then the markers' placement.

    Returns:
        (vertices float32, faces int32, colours uint8, ``{"stool": [start, end], "floor_markers":
        [start, end]}``): the props' vertex ranges in the returned mesh.
    """
    floor = float(body[:, 1].min())
    parts, ranges, n = [(v, f, colors)], {}, len(v)
    if stool:
        parts.append(stool_mesh(body, floor, rng))
        ranges["stool"] = [n, n + len(parts[-1][0])]
        n += len(parts[-1][0])
    if markers > 0:
        parts.append(floor_markers(body, floor, markers, rng))
        ranges["floor_markers"] = [n, n + len(parts[-1][0])]
    mv, mf, mc = merge_meshes(parts)
    return mv.astype(np.float32), mf.astype(np.int32), mc, ranges
