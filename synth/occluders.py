"""Objects in front of the people: boxes (a crate, a table, a low wall, a car's flank) and cylinders
(a post, a bin, a tree trunk) standing on the ground between the camera and a person.

Real photographs show people behind things; a network that has only seen whole, unobstructed
bodies guesses badly where a table hides the legs. Training-side occluders (``data.effects`` of
``recovery``) paste a patch over a crop; these are in the scene: they are lit by the same sky, cast
shadows on the ground and on the people, and the labels stay exact because they come from the same
label pass (the ray through each pixel centre): a pixel where an occluder is hit first belongs to no
person (mask, parts, bones 0, depth 0, correspondence -1), and a keypoint whose pixel shows the
occluder is not visible.

Placement (:func:`place_occluders`), per sample with probability ``occluders.prob``, 1 to
``occluders.max`` of them, each in front of a person drawn at random: on the ground line from the
person's footprint towards the camera, between the person's footprint (plus ``people.gap``) and
2 m from it, and no more than 60 % of the way to the camera (so that it hides a part of the person,
not the whole picture), shifted sideways by up to the person's footprint
radius, never overlapping any person's footprint disc or another occluder's. Sizes (metres): a box
0.3-1.4 wide, 0.3-0.9 deep, 0.4-1.3 high, turned to face the camera within 25 degrees; a cylinder
of radius 0.04-0.3 and height 0.5-2.5. Colours from a palette of wood, concrete, metal, white,
black and painted colours, with a little grain per vertex. A placement that finds no room after
20 tries leaves that occluder out (the sample's ``occluders`` lists the ones placed).

Every occluder of a kind has the same topology (:func:`occluder_faces`), so one renderer serves
every sample; unused slots are hidden like unused person slots.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

KINDS = ("box", "cylinder")
SEGMENTS = 32  # a cylinder's sides
# Linear RGB albedos: wood, dark wood, concrete, metal, white, black, red, blue, green, yellow.
PALETTE = np.array([
    [0.30, 0.17, 0.08], [0.12, 0.06, 0.03], [0.35, 0.34, 0.32], [0.45, 0.46, 0.48], [0.75, 0.75, 0.72],
    [0.03, 0.03, 0.03], [0.45, 0.04, 0.03], [0.04, 0.10, 0.35], [0.06, 0.22, 0.06], [0.60, 0.45, 0.05],
])  # fmt: skip


@dataclass(frozen=True)
class Occluder:
    """One object on the ground (JSON-able: the sample's ``occluders[i]``).

    Attributes:
        kind: "box" or "cylinder".
        centre: (x, z) of its footprint's centre on the ground (y = 0), metres.
        size: box (width, height, depth); cylinder (radius, height, radius), metres.
        yaw: radians about +Y (the box's width along its rotated x axis).
        colour: linear RGB albedo.
        seed: the seed of its grain.
    """

    kind: str
    centre: tuple[float, float]
    size: tuple[float, float, float]
    yaw: float
    colour: tuple[float, float, float]
    seed: int

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"occluder kind must be box or cylinder, got {self.kind!r}")
        if len(self.size) != 3 or min(self.size) <= 0:
            raise ValueError(f"occluder size must be 3 positive lengths, got {self.size}")

    @property
    def radius(self) -> float:
        """The radius of its footprint's bounding disc."""
        w, _, d = self.size
        return 0.5 * math.hypot(w, d) if self.kind == "box" else w

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "centre": [round(c, 6) for c in self.centre], "size": [round(s, 6) for s in self.size],
                "yaw": round(self.yaw, 6), "colour": [round(c, 6) for c in self.colour], "seed": int(self.seed)}  # fmt: skip

    @staticmethod
    def from_json(d: dict[str, Any]) -> Occluder:
        try:
            return Occluder(str(d["kind"]), tuple(float(c) for c in d["centre"]), tuple(float(s) for s in d["size"]),
                            float(d["yaw"]), tuple(float(c) for c in d["colour"]), int(d["seed"]))  # fmt: skip
        except (KeyError, TypeError) as exc:
            raise ValueError(f"occluder lacks or mistypes {exc}") from None


@cache
def _unit_mesh(kind: str) -> tuple[np.ndarray, np.ndarray]:
    """A unit box ([-0.5, 0.5] in x and z, [0, 1] in y; 4 vertices per side for flat normals) or a
    unit cylinder (radius 1, height 1; sides and caps apart), and their outward faces."""
    if kind == "box":
        quads = []
        for axis in range(3):
            for sign in (-1.0, 1.0):
                u, v = [a for a in range(3) if a != axis]
                corners = []
                for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                    p = np.zeros(3)
                    p[axis], p[u], p[v] = sign, a, b
                    corners.append(p)
                c = np.array(corners) * 0.5
                n = np.zeros(3)
                n[axis] = sign
                if np.cross(c[1] - c[0], c[2] - c[0]) @ n < 0:
                    c = c[::-1]
                quads.append(c)
        v = np.concatenate(quads) + np.array([0.0, 0.5, 0.0])
        f = np.concatenate([4 * q + np.array([[0, 1, 2], [0, 2, 3]]) for q in range(6)])
        return v, f.astype(np.int32)
    t = 2 * math.pi * np.arange(SEGMENTS) / SEGMENTS
    ring = np.stack([np.cos(t), np.zeros(SEGMENTS), np.sin(t)], 1)
    side = np.concatenate([ring, ring + [0.0, 1.0, 0.0]])
    caps = np.concatenate([[[0.0, 0.0, 0.0]], ring, [[0.0, 1.0, 0.0]], ring + [0.0, 1.0, 0.0]])
    v = np.concatenate([side, caps])
    k = np.arange(SEGMENTS)
    k1 = (k + 1) % SEGMENTS
    faces = [np.stack([k, k + SEGMENTS, k1], 1), np.stack([k1, k + SEGMENTS, k1 + SEGMENTS], 1)]
    b, top = 2 * SEGMENTS, 3 * SEGMENTS + 1
    faces += [np.stack([np.full(SEGMENTS, b), b + 1 + k, b + 1 + k1], 1),
              np.stack([np.full(SEGMENTS, top), top + 1 + k1, top + 1 + k], 1)]  # fmt: skip
    f = np.concatenate(faces)
    # Outward winding: flip the faces whose normal points towards the axis (or down at the bottom).
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    c = tri.mean(1)
    out = np.where(np.abs(n[:, 1]) > 1e-9, np.sign(c[:, 1] - 0.5) * n[:, 1], (c[:, [0, 2]] * n[:, [0, 2]]).sum(1))
    f[out < 0] = f[out < 0][:, ::-1]
    return v, f.astype(np.int32)


def occluder_faces(kind: str) -> np.ndarray:
    """(F, 3) int32 faces of every occluder of ``kind``."""
    return _unit_mesh(kind)[1]


def occluder_vertex_count(kind: str) -> int:
    return len(_unit_mesh(kind)[0])


def occluder_mesh(o: Occluder) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(V, 3) float64 world vertices, (F, 3) faces and (V, 3) linear colours of ``o``."""
    v, f = _unit_mesh(o.kind)
    s = np.array(o.size, np.float64)
    p = v * s
    c, sn = math.cos(o.yaw), math.sin(o.yaw)
    rot = np.array([[c, 0.0, sn], [0.0, 1.0, 0.0], [-sn, 0.0, c]])
    p = p @ rot.T + np.array([o.centre[0], 0.0, o.centre[1]])
    grain = 1.0 + 0.06 * np.random.default_rng(o.seed).standard_normal(len(p))
    colours = np.clip(np.asarray(o.colour)[None] * grain[:, None], 0.0, 1.0)
    return p, f, colours


def draw_colour(rng: np.random.Generator) -> np.ndarray:
    """(3,) a linear albedo: a colour of :data:`PALETTE` varied by +-15 % per channel."""
    return PALETTE[int(rng.integers(len(PALETTE)))] * rng.uniform(0.85, 1.15, 3)


def _camera_centre(camera: Any) -> np.ndarray:
    return -np.asarray(camera.R, np.float64).T @ np.asarray(camera.t, np.float64)


def place_occluders(footprints: list[tuple[np.ndarray, float]], camera: Any, prob: float, most: int, gap: float,
                    rng: np.random.Generator) -> list[Occluder]:
    """Draw the sample's occluders (the module docstring's rules).

    Args:
        footprints: per person, the (x, z) centre and radius of its footprint disc (placed).
        camera: the sample's camera (its centre is kept clear).
        prob: the probability that the sample has any; ``most`` the most it has.
        gap: the least distance between footprint discs, metres.
        rng: the sample's random generator.
    """
    if not footprints or rng.uniform() >= prob:
        return []
    cam = _camera_centre(camera)[[0, 2]]
    discs = [(np.asarray(c, np.float64), float(r)) for c, r in footprints]
    out: list[Occluder] = []
    for _ in range(int(rng.integers(1, most + 1))):
        for _ in range(20):
            o = _draw(discs, cam, gap, rng)
            if o is not None:
                out.append(o)
                discs.append((np.array(o.centre), o.radius))
                break
    return out


def _draw(discs: list[tuple[np.ndarray, float]], cam: np.ndarray, gap: float, rng: np.random.Generator) -> Occluder | None:
    """One candidate occluder in front of a random person, or None where it does not fit."""
    centre, r_p = discs[int(rng.integers(len(discs)))]
    to_cam = cam - centre
    dist = float(np.linalg.norm(to_cam))
    kind = KINDS[int(rng.integers(2))]
    if kind == "box":
        size = (rng.uniform(0.3, 1.4), rng.uniform(0.4, 1.3), rng.uniform(0.3, 0.9))
    else:
        radius = rng.uniform(0.04, 0.3)
        size = (radius, rng.uniform(0.5, 2.5), radius)
    u = to_cam / max(dist, 1e-9)
    side = np.array([-u[1], u[0]])
    yaw = math.atan2(u[0], u[1]) + math.radians(rng.uniform(-25.0, 25.0))
    colour = draw_colour(rng)
    seed = int(rng.integers(2**31))
    probe = Occluder(kind, (0.0, 0.0), tuple(float(s) for s in size), yaw, tuple(float(c) for c in colour), seed)
    lo, hi = r_p + gap + probe.radius, min(r_p + 2.0, 0.6 * dist - probe.radius)
    if hi <= lo:
        return None
    at = centre + rng.uniform(lo, hi) * u + rng.uniform(-1.0, 1.0) * r_p * side
    o = Occluder(kind, (float(at[0]), float(at[1])), probe.size, yaw, probe.colour, seed)
    for c, r in discs:
        if np.linalg.norm(at - c) < r + o.radius + gap:
            return None
    if np.linalg.norm(at - cam) < o.radius + 0.6:
        return None
    return Occluder.from_json(o.to_json())  # rounded as stored
