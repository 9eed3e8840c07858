"""Procedural hair for the stand-in people: strands grown over the scalp, posed with the head.

Anny's people have no hair, and a hair colour painted on the scalp reads as a helmet. This module
grows hair geometry for a subject in the model's rest frame, the way real-time engines build "hair
cards": ``NUM_STRANDS`` narrow ribbons, each a polyline of ``POINTS`` points, rooted on the scalp and
combed by a per-style direction field while they lie on the head, falling under gravity where they
leave it, and kept off the skin by the body's own surface:

- **roots** are spread over the scalp in proportion to area, above a hairline high at the forehead,
  at the ears on the sides and low at the nape (the same curve as the painted cap of
  :mod:`synth.textures`, so the scalp under the strands has the hair's colour);
- **growth**: each strand steps along its style's direction, projected on the tangent plane of the
  nearest body vertex and held at its own height over the skin (its layer, ``volume`` at most), so
  strands stack into a volume instead of a shell. Styles (``STYLES``): ``short`` and ``curly``
  combed from the crown; ``long`` combed from a parting, leaving the head where it curves away
  below and then hanging down, sliding over the shoulders and back; ``tied`` combed to a point at the
  back of the head and gathered there into a ponytail. ``curl`` winds a strand as a helix (curly
  hair; long hair is sometimes wavy);
- **ribbons**: each point becomes two vertices across the strand, ``width`` wide at the root and
  40 % of it at the tip, facing away from the skin; every hair has the same topology
  (:func:`hair_faces`), so a renderer built once serves every subject and style;
- **colour**: per vertex (Mitsuba's ``mesh_attribute``), the subject's hair colour varied per strand
  and along it (darker roots, lighter or darker tips);
- **skinning**: every hair vertex takes the LBS weights of the nearest body vertex of its strand's
  attachment (the skin it lies on, for strands on the head; for hanging points the nearest skin),
  smoothed along the strand, so roots move exactly with the scalp and long hair follows the neck and
  shoulders. Hair is not simulated: posed hair can pass through a raised arm or a shoulder pulled up
  against it, and long hair keeps its rest shape (hanging straight down at rest) when the person
  bends over.

Everything is a function of the subject's rest mesh and the :class:`HairSpec`, whose ``seed`` fixes
the random choices: the sample's JSON stores the spec, and ``synth validate`` rebuilds the same
hair from it (:func:`subject_hair`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

STYLES = ("short", "long", "tied", "curly")
NUM_STRANDS = 1500
POINTS = 14  # points per strand
_DENSE = 64  # growth steps per strand before resampling to POINTS

# Per style: strand length (tied: the ponytail's), volume (the highest layer over the skin), ribbon
# width at the root, curl radius (metres), each drawn uniformly in its range.
LENGTH = {"short": (0.03, 0.08), "long": (0.20, 0.40), "tied": (0.10, 0.28), "curly": (0.05, 0.13)}
VOLUME = {"short": (0.005, 0.012), "long": (0.006, 0.016), "tied": (0.002, 0.006), "curly": (0.02, 0.045)}
WIDTH = {"short": (0.008, 0.012), "long": (0.008, 0.013), "tied": (0.010, 0.015), "curly": (0.007, 0.010)}
CURL = {"short": (0.0, 0.0), "long": (0.0, 0.012), "tied": (0.0, 0.0), "curly": (0.008, 0.018)}
WAVY_LONG = 0.3  # share of long hair that is wavy (curl > 0)
_SKIN_GAP = 0.002  # metres: a strand's root over the skin, and its least height anywhere
_COLLIDE_BONES = ("head", "neck", "spine_03", "spine_02", "clavicle_l", "clavicle_r")


@dataclass(frozen=True)
class HairSpec:
    """One person's hair (JSON-able: the sample's ``people[i].hair``).

    Attributes:
        style: one of ``STYLES``.
        length: strand length in metres (``tied``: the ponytail's length below the tie).
        volume: the highest strand layer over the skin, metres.
        width: ribbon width at the root, metres.
        curl: helix radius, metres (0: straight).
        colour: linear RGB albedo.
        seed: the seed of every random choice of :func:`build_hair`.
    """

    style: str
    length: float
    volume: float
    width: float
    curl: float
    colour: tuple[float, float, float]
    seed: int

    def __post_init__(self) -> None:
        if self.style not in STYLES:
            raise ValueError(f"hair style must be one of {', '.join(STYLES)}, got {self.style!r}")
        if not (self.length > 0 and self.volume >= 0 and self.width > 0 and self.curl >= 0):
            raise ValueError(f"hair length and width must be positive, volume and curl non-negative: {self}")
        if len(self.colour) != 3:
            raise ValueError(f"hair colour must be RGB, got {self.colour}")

    def to_json(self) -> dict[str, Any]:
        return {
            "style": self.style, "length": round(self.length, 6), "volume": round(self.volume, 6),
            "width": round(self.width, 6), "curl": round(self.curl, 6),
            "colour": [round(float(c), 6) for c in self.colour], "seed": int(self.seed),
        }  # fmt: skip

    @staticmethod
    def from_json(d: dict[str, Any]) -> HairSpec:
        return HairSpec(
            style=str(d["style"]), length=float(d["length"]), volume=float(d["volume"]), width=float(d["width"]),
            curl=float(d["curl"]), colour=tuple(float(c) for c in d["colour"]), seed=int(d["seed"]),
        )  # fmt: skip


def sample_hair(rng: np.random.Generator, styles: dict[str, float], colour: Any) -> HairSpec:
    """Draw a hair: the style by the weights ``styles`` (style name -> weight), its sizes uniformly
    in the style's ranges (``LENGTH``, ``VOLUME``, ``WIDTH``, ``CURL``), ``colour`` as given. The
    spec is rounded as stored, so the hair rebuilt from a sample's JSON is the one rendered."""
    names = [s for s in STYLES if styles.get(s, 0.0) > 0]
    if not names:
        raise ValueError("hair styles: at least one style needs a positive weight")
    w = np.array([styles[s] for s in names], np.float64)
    style = names[int(rng.choice(len(names), p=w / w.sum()))]
    length, volume, width = (float(rng.uniform(*t[style])) for t in (LENGTH, VOLUME, WIDTH))
    curl = float(rng.uniform(*CURL[style]))
    if style == "long" and rng.uniform() >= WAVY_LONG:
        curl = 0.0
    spec = HairSpec(style, length, volume, width, curl, tuple(float(c) for c in np.asarray(colour)[:3]),
                    int(rng.integers(2**31)))  # fmt: skip
    return HairSpec.from_json(spec.to_json())


@dataclass(frozen=True)
class HairMesh:
    """A hair in the rest frame: ``vertices`` (H, 3), ``faces`` (:func:`hair_faces`), ``colours``
    (H, 3) linear RGB, ``weights`` (H, J) LBS weights (rows sum to 1)."""

    vertices: np.ndarray
    faces: np.ndarray
    colours: np.ndarray
    weights: np.ndarray


@lru_cache(maxsize=1)
def hair_faces() -> np.ndarray:
    """(F, 3) int32 faces of every hair: two triangles per strand segment (the same for all hair)."""
    k = np.arange(POINTS - 1)
    quad = np.stack([2 * k, 2 * k + 2, 2 * k + 1, 2 * k + 1, 2 * k + 2, 2 * k + 3], 1).reshape(-1, 3)
    base = (2 * POINTS * np.arange(NUM_STRANDS))[:, None, None]
    faces = (quad[None] + base).reshape(-1, 3).astype(np.int32)
    faces.setflags(write=False)
    return faces


def num_vertices() -> int:
    return 2 * POINTS * NUM_STRANDS


def _unit(v: np.ndarray, fallback: np.ndarray | None = None) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    out = v / np.maximum(n, 1e-12)
    if fallback is not None:
        out = np.where(n > 1e-9, out, fallback)
    return out


def build_hair(
    vertices: np.ndarray,
    faces: np.ndarray,
    weights: np.ndarray,
    bone_names: list[str] | tuple[str, ...],
    joints: np.ndarray,
    spec: HairSpec,
) -> HairMesh:
    """Grow ``spec``'s hair on a body in the rest frame (see the module docstring).

    Args:
        vertices: (V, 3) rest-pose body vertices, metres (Y up, facing +Z).
        faces: (F, 3) the body's faces (outward winding).
        weights: (V, J) the body's LBS weights.
        bone_names: (J,) bone names, including head, neck, spine_02, spine_03 and the clavicles.
        joints: (J, 3) rest positions of the bone heads.
        spec: the hair.

    Raises:
        ValueError: a body without the bones above, or without a head to grow hair on.
    """
    body = _Body.of(vertices, faces, weights, bone_names, joints)
    rng = np.random.default_rng(spec.seed)
    roots, root_n = _roots(body, rng)
    growth = _Growth(body, roots, root_n, spec, rng)
    growth.run()
    pts, nearest, hanging, u, total = _resample(growth)
    frac = u / total  # 0 at the root, 1 at the tip
    tang = _unit(np.gradient(pts, axis=1))
    if spec.curl > 0:
        pts, tang = _curl(pts, tang, u, frac, total, spec, rng)
    # Every point off the skin (a curl can wind a strand into it, resampling can cut a corner).
    flat = pts.reshape(-1, 3)
    v, n, _ = body.skin(flat)
    flat += np.maximum(_SKIN_GAP - ((flat - v) * n).sum(1), 0.0)[:, None] * n
    pts = flat.reshape(pts.shape)
    # Ribbons facing away from the skin under them.
    out = body.normals[nearest]
    across = _unit(np.cross(tang, out), _unit(np.cross(tang, np.array([0.0, 0.0, 1.0]))))
    half = 0.5 * spec.width * (1.0 - 0.6 * frac)[..., None] * rng.uniform(0.7, 1.3, (NUM_STRANDS, 1, 1))
    ribbon = np.stack([pts - half * across, pts + half * across], 2).reshape(-1, 3)
    colours = _colours(spec, frac, total, rng)
    weights_out = _strand_weights(body, pts, nearest, hanging, growth.let_go)
    return HairMesh(
        vertices=ribbon.astype(np.float32), faces=hair_faces(), colours=colours.astype(np.float32),
        weights=weights_out.astype(np.float32),
    )  # fmt: skip


@dataclass(frozen=True)
class _Body:
    """The body a hair grows on, in the rest frame, and the head's frame.

    Attributes:
        vertices: (V, 3) float64; ``faces`` (F, 3); ``weights`` (V, J); ``normals`` (V, 3) unit.
        vb: (V,) each vertex's dominant bone; ``bi`` bone name -> index.
        jh: (3,) the head joint; ``up`` (U, 3) the head's vertices above it, ``h_head`` their
            height over it.
        cx, cz: the middle of the head in x and z; ``centre`` (3,) the skull's centre, ``radius``
            half its depth, ``half_x`` half its width (plus 1 cm).
        near: (V,) bool, the skin strands grow on and are kept off: the head, neck, chest and
            clavicles (not the arms, along which hanging strands would slide).
    """

    vertices: np.ndarray
    faces: np.ndarray
    weights: np.ndarray
    normals: np.ndarray
    vb: np.ndarray
    bi: dict[str, int]
    jh: np.ndarray
    up: np.ndarray
    h_head: float
    cx: float
    cz: float
    centre: np.ndarray
    radius: float
    half_x: float
    near: np.ndarray
    near_idx: np.ndarray
    tree: Any

    @staticmethod
    def of(vertices, faces, weights, bone_names, joints) -> _Body:
        from scipy.spatial import cKDTree

        from blsm.mesh import vertex_normals

        vertices = np.asarray(vertices, np.float64)
        bi = {n: i for i, n in enumerate(bone_names)}
        if missing := [b for b in _COLLIDE_BONES if b not in bi]:
            raise ValueError(f"hair needs the bones {missing}")
        vb = np.asarray(weights).argmax(1)
        jh = np.asarray(joints[bi["head"]], np.float64)
        head = vb == bi["head"]
        up = vertices[head & (vertices[:, 1] > jh[1])]
        if len(up) < 20:
            raise ValueError("the body has no head to grow hair on")
        h_head = float(up[:, 1].max() - jh[1])
        cx, cz = 0.5 * (up[:, 0].min() + up[:, 0].max()), 0.5 * (up[:, 2].min() + up[:, 2].max())
        centre = np.array([cx, jh[1] + 0.55 * h_head, cz])
        radius = 0.5 * float(up[:, 2].max() - up[:, 2].min())
        half_x = 0.5 * float(up[:, 0].max() - up[:, 0].min()) + 0.01
        normals = vertex_normals(vertices, np.asarray(faces, np.int64))
        near = np.isin(vb, [bi[b] for b in _COLLIDE_BONES])
        return _Body(vertices, faces, weights, normals, vb, bi, jh, up, h_head, cx, cz, centre, radius, half_x,
                     near, np.flatnonzero(near), cKDTree(vertices[near]))  # fmt: skip

    def skin(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The nearest skin vertex (of ``near``) to each point of ``p`` (N, 3): position, normal, index."""
        i = self.near_idx[self.tree.query(p)[1]]
        return self.vertices[i], self.normals[i], i


def _roots(body: _Body, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) roots and their (N, 3) skin normals: area-weighted points of the scalp faces above
    the hairline."""
    vertices, faces, jh, h_head, bi, vb = body.vertices, body.faces, body.jh, body.h_head, body.bi, body.vb
    tri = vertices[faces]
    fc = tri.mean(1)
    back = rng.uniform(-0.35, 0.1)
    front = rng.uniform(0.72, 0.76)  # at or above the painted cap's front (0.72), which fills in
    # Front and back about the vertical through the head joint (the face's centre would count the
    # chin and throat as "back", where the hairline is lowest).
    fh = (fc[:, 2] - jh[2]) / np.maximum(np.hypot(fc[:, 0] - body.cx, fc[:, 2] - jh[2]), 1e-9)  # +1 front, -1 back
    hairline = jh[1] + h_head * (0.45 + (front - back) / 2 * fh + (back + front - 0.9) / 2 * fh**2)
    scalp = np.isin(vb[faces], [bi["head"], bi["neck"]]).all(1) & (fc[:, 1] > hairline)
    scalp &= (fc[:, 2] < jh[2]) | (fc[:, 1] > jh[1] + 0.3 * h_head)  # never the throat or chin
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) * scalp
    if area.sum() <= 0:
        raise ValueError("the body has no scalp above the hairline")
    f = rng.choice(len(faces), NUM_STRANDS, p=area / area.sum())
    r1, r2 = np.sqrt(rng.uniform(size=NUM_STRANDS)), rng.uniform(size=NUM_STRANDS)
    bary = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], 1)
    roots = np.einsum("nk,nkc->nc", bary, tri[f])
    root_n = _unit(np.einsum("nk,nkc->nc", bary, body.normals[faces[f]]))
    return roots, root_n


_DOWN = np.array([0.0, -1.0, 0.0])


class _Growth:
    """The growth of every strand (module docstring), ``_DENSE`` steps of one length.

    After :meth:`run`: ``path`` the (N, 3) points of each step, ``anchor`` (D + 1, N) the skin
    vertex each point lies over, ``hang`` (D + 1, N) the length hanging off the scalp (loose or in
    the tail), ``let_go`` (N,) the skin vertex under the last point on the scalp.
    """

    def __init__(self, body: _Body, roots: np.ndarray, root_n: np.ndarray, spec: HairSpec,
                 rng: np.random.Generator) -> None:
        self.body, self.spec = body, spec
        layer = rng.uniform(size=NUM_STRANDS) ** 0.7  # more strands in the outer layers
        self.height = _SKIN_GAP + spec.volume * layer
        self.crown = body.centre + body.radius * _unit(np.array([0.0, 0.75, -0.65]))
        self.part_x = body.cx + rng.uniform(-0.6, 0.6) * body.radius * (rng.uniform() < 0.7)
        # The tie (tied hair) on the back of the head: the skin point in that direction, raised by the
        # hair's volume.
        self.aim = _unit(np.array([0.0, rng.uniform(-0.2, 0.3), -1.0]))
        on_ray = body.up[np.argmax(_unit(body.up - body.centre) @ self.aim)]
        self.tie = on_ray + (_SKIN_GAP + spec.volume + 0.005) * self.aim
        self.tail_dir = _unit(np.array([0.0, -1.0, -rng.uniform(0.1, 0.5)]))
        if spec.style == "tied":
            path_len = 2.0 * math.pi * body.radius * 0.6 + spec.length  # at most: over the head, then the tail
        else:
            path_len = spec.length
        self.step = path_len / _DENSE
        self.pos = roots + _SKIN_GAP * root_n
        self.dirn = np.zeros_like(self.pos)
        self.attached = np.ones(NUM_STRANDS, bool)
        self.tail = np.zeros(NUM_STRANDS, bool)  # tied: in the ponytail
        self.tail_start = np.zeros(NUM_STRANDS)
        spread = rng.normal(size=(NUM_STRANDS, 3)) * 0.35
        self.spread = spread - (spread @ self.tail_dir)[:, None] * self.tail_dir
        self.s = np.zeros(NUM_STRANDS)
        self.path = [self.pos.copy()]
        self.anchor = np.empty((_DENSE + 1, NUM_STRANDS), np.int64)
        self.anchor[0] = body.skin(self.pos)[2]
        self.hang = np.zeros((_DENSE + 1, NUM_STRANDS))
        self.let_go = self.anchor[0].copy()

    def run(self) -> None:
        for k in range(_DENSE):
            self._advance(k, self.pos + self.step * self._direction(k))

    def _direction(self, k: int) -> np.ndarray:
        """(N, 3) unit step directions: the style's comb on the skin's tangent plane; hanging
        strands towards gravity, with the inertia of the last step."""
        body, spec, pos = self.body, self.spec, self.pos
        _, n, _ = body.skin(pos)
        if spec.style in ("short", "curly"):
            g = _unit(pos - self.crown) + 0.4 * _DOWN
        elif spec.style == "long":  # from the parting, sideways and back off the face, then down
            side = np.sign(pos[:, 0] - self.part_x)[:, None] * np.array([1.0, 0.0, 0.0])
            fr = np.clip((pos[:, 2] - body.cz) / body.radius, 0.0, 1.0)[:, None]
            g = (0.6 + 1.5 * fr) * side + (1.2 - 0.6 * fr) * _DOWN + (0.4 + 1.2 * fr) * np.array([0.0, 0.0, -1.0])
        else:
            g = self.tie - pos
        t = g - (g * n).sum(1, keepdims=True) * n
        t = _unit(t, self.dirn if k else _unit(g))
        free = ~self.attached
        if free.any():
            t[free] = _unit(0.5 * self.dirn[free] + _DOWN)
        return t

    def _advance(self, k: int, new: np.ndarray) -> None:
        """Step ``k`` to the points ``new``: the ponytail gathered at the tie, strands held at their
        layer over the skin, long hair let go of the head."""
        body, spec, pos, s, step = self.body, self.spec, self.pos, self.s, self.step
        if spec.style == "tied":
            tail, tail_start = self.tail, self.tail_start
            at_tie = ~tail & (np.linalg.norm(new - self.tie, axis=1) < 0.025)
            tail |= at_tie
            tail_start[at_tie] = s[at_tie]
            d = np.maximum(s + step - tail_start, 0.0)[:, None]
            out_d = 0.04 * (1.0 - np.exp(-d / 0.03))  # first away from the head, then down
            fan = self.tie + out_d * self.aim + (d - out_d) * self.tail_dir + np.minimum(0.012 + 0.12 * d, 0.04) * self.spread
            new = np.where(tail[:, None], fan, new)
            done = tail & (s - tail_start >= spec.length)
            new[done] = pos[done]
        v2, n2, i2 = body.skin(new)
        h = ((new - v2) * n2).sum(1)
        ramp = np.minimum(1.0, (s + step) / 0.02)  # strands rise from the scalp to their layer
        height = self.height
        target = _SKIN_GAP + (height - _SKIN_GAP) * ramp
        snap = self.attached & ~self.tail
        new[snap] += ((target - h)[snap])[:, None] * n2[snap]
        low = ~snap & (h < _SKIN_GAP + 0.5 * (height - _SKIN_GAP))
        new[low] += ((_SKIN_GAP + 0.5 * (height - _SKIN_GAP) - h)[low])[:, None] * n2[low]
        if spec.style == "long":
            # Leave the head where it curves away below, or below the ears, but not over the face.
            cx, cz, jh, h_head = body.cx, body.cz, body.jh, body.h_head
            beside = new[:, 2] - cz < 0.3 * body.radius
            self.attached &= ~(beside & ((n2[:, 1] < -0.1) | (new[:, 1] < jh[1] + 0.25 * h_head)))
            # Hanging hair stays out of the face: pushed sideways out of the box in front of it.
            face = ~self.attached & (new[:, 2] > cz) & (np.abs(new[:, 0] - cx) < body.half_x) & (new[:, 1] > jh[1] - 0.1 * h_head)
            new[face, 0] = cx + np.where(new[face, 0] >= cx, 1.0, -1.0) * body.half_x
        moved = np.linalg.norm(new - pos, axis=1)
        self.dirn = _unit(new - pos, self.dirn)
        self.s = s + moved
        self.pos = new
        self.path.append(new.copy())
        self.anchor[k + 1] = i2
        on_scalp = self.attached & ~self.tail
        self.let_go[on_scalp] = i2[on_scalp]
        self.hang[k + 1] = np.where(on_scalp, 0.0, self.hang[k] + moved)


def _resample(growth: _Growth) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each strand resampled to ``POINTS`` points evenly along its length: the points (N, P, 3), the
    skin vertex under each (N, P), the length hanging off the scalp there (N, P), the arc length
    (N, P) and the strand's length (N, 1)."""
    dense = np.stack(growth.path, 1)  # (N, D + 1, 3)
    seg = np.linalg.norm(np.diff(dense, axis=1), axis=2)
    arc = np.concatenate([np.zeros((NUM_STRANDS, 1)), np.cumsum(seg, 1)], 1)
    total = np.maximum(arc[:, -1:], 1e-9)
    u = np.linspace(0.0, 1.0, POINTS)[None] * total
    pts = np.empty((NUM_STRANDS, POINTS, 3))
    nearest = np.empty((NUM_STRANDS, POINTS), np.int64)
    hanging = np.empty((NUM_STRANDS, POINTS))
    for i in range(NUM_STRANDS):
        for c in range(3):
            pts[i, :, c] = np.interp(u[i], arc[i], dense[i, :, c])
        nearest[i] = growth.anchor[:, i][np.clip(np.searchsorted(arc[i], u[i]), 0, _DENSE)]
        hanging[i] = np.interp(u[i], arc[i], growth.hang[:, i])
    return pts, nearest, hanging, u, total


def _curl(pts: np.ndarray, tang: np.ndarray, u: np.ndarray, frac: np.ndarray, total: np.ndarray,
          spec: HairSpec, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The strands wound into helices of radius ``spec.curl`` (rising from the root over 3 cm), and
    their new tangents."""
    e1 = _unit(np.cross(tang, np.array([0.0, 1.0, 0.0])), np.array([1.0, 0.0, 0.0]))
    e2 = np.cross(tang, e1)
    period = rng.uniform(0.025, 0.045, (NUM_STRANDS, 1))
    phi = 2 * math.pi * u / period + rng.uniform(0, 2 * math.pi, (NUM_STRANDS, 1))
    amp = spec.curl * np.minimum(1.0, frac * total / 0.03)[..., None]
    pts = pts + amp * (np.cos(phi)[..., None] * e1 + np.sin(phi)[..., None] * e2)
    return pts, _unit(np.gradient(pts, axis=1))


def _colours(spec: HairSpec, frac: np.ndarray, total: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(H, 3) linear RGB per ribbon vertex: the hair's colour varied per strand and along it (darker
    roots, lighter or darker tips)."""
    base = np.asarray(spec.colour, np.float64)
    strand = np.exp(rng.normal(0.0, 0.12, (NUM_STRANDS, 1)))
    tip = rng.uniform(-0.1, 0.25)
    along = (0.8 + 0.2 * np.minimum(1.0, frac * total / 0.01)) * (1.0 + tip * frac)
    colours = np.clip(base[None, None] * (strand * along)[..., None], 0.0, 1.0)
    return np.repeat(colours, 2, axis=1).reshape(-1, 3)


def _strand_weights(body: _Body, pts: np.ndarray, nearest: np.ndarray, hanging: np.ndarray,
                    let_go: np.ndarray) -> np.ndarray:
    """(H, J) LBS weights per ribbon vertex: the skin's under each point, smoothed along the strand
    (roots keep their own). Hair hanging off the scalp (a ponytail, long hair below the head) goes
    over from the weights where it left the scalp to those of the nearest skin below the head within
    15 cm, so that it hangs from the neck and shoulders instead of turning stiffly with the head."""
    from scipy.spatial import cKDTree

    weights = body.weights
    w = np.asarray(weights, np.float64)[nearest]  # (N, P, J)
    if (hanging > 0).any():
        body_idx = np.flatnonzero(body.near & (body.vb != body.bi["head"]))
        below = body_idx[cKDTree(body.vertices[body_idx]).query(pts.reshape(-1, 3))[1]].reshape(NUM_STRANDS, POINTS)
        a = np.clip(hanging / 0.15, 0.0, 1.0)[..., None]
        w = np.where(hanging[..., None] > 0, (1 - a) * np.asarray(weights, np.float64)[let_go][:, None] + a * np.asarray(weights, np.float64)[below], w)
    sm = w.copy()
    for _ in range(2):
        sm[:, 1:-1] = 0.25 * sm[:, :-2] + 0.5 * sm[:, 1:-1] + 0.25 * sm[:, 2:]
        sm[:, -1] = 0.5 * (sm[:, -2] + sm[:, -1])
        sm[:, 0] = w[:, 0]
    sm /= sm.sum(-1, keepdims=True)
    return np.repeat(sm, 2, axis=1).reshape(-1, sm.shape[-1])


def pose_hair(hair: HairMesh, transforms: Any) -> np.ndarray:
    """(H, 3) float32 posed hair: LBS of the rest hair with the body's (J, 3, 4) skinning transforms."""
    import torch

    from blsm.lbs import linear_blend_skinning

    tr = torch.as_tensor(np.asarray(transforms), dtype=torch.float32)
    v = linear_blend_skinning(torch.as_tensor(hair.vertices)[None], torch.as_tensor(hair.weights), tr[None, :, :, :3], tr[None, :, :, 3])
    return v[0].numpy().astype(np.float32)


HAIR_STREAM = 0x68616972  # "hair": the random stream of the hair of a dataset's subjects


def subject_hair_spec(subject: Any, styles: dict[str, float], seed: int) -> HairSpec:
    """The hair of ``subject`` in a dataset of seed ``seed``: drawn from a generator seeded by the
    dataset seed and the subject's id (so it does not depend on which worker draws it), in the
    colour of the subject's painted hair (``meta.outfit.hair``; for subjects without an outfit, a
    colour of the palette of :mod:`synth.textures`)."""
    import zlib

    rng = np.random.default_rng([int(seed), zlib.crc32(str(subject.id).encode()), HAIR_STREAM])
    colour = subject.meta.get("outfit", {}).get("hair")
    if colour is None:
        from synth.textures import sample_outfit

        colour = sample_outfit(rng).hair
    return sample_hair(rng, styles, colour)


def subject_hair(subject: Any, model: Any, spec: HairSpec, pipeline: str) -> HairMesh:
    """Grow ``spec`` on the body the ``pipeline`` poses: the subject's template with its painted
    weights (``rigged``) or the registration's rest mesh with the model's weights (``blsm``). The
    ``raw`` pipeline shows scans as captured and has no grown hair (a ValueError)."""
    import torch

    from synth.subjects import registration_output

    if pipeline == "raw":
        raise ValueError("the raw pipeline shows each scan as captured: no hair is grown on it")
    with torch.no_grad():
        _, _, out = registration_output(model, subject.registration)
    joints = out.rest_joints[0].numpy()
    names = list(model.bone_names)
    if pipeline == "rigged":
        return build_hair(subject.template, subject.faces, subject.weights, names, joints, spec)
    disp = torch.as_tensor(np.asarray(subject.registration["displacement"]), dtype=torch.float32)
    rest = (out.template[0] + disp).numpy()
    return build_hair(rest, model.faces.numpy(), model.weights.numpy(), names, joints, spec)
