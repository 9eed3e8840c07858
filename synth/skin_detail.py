"""Skin, face and hand detail painted over a procedural albedo (:mod:`synth.textures`).

A flat skin tone on a face without features reads as a mannequin. :func:`paint_detail` paints, into
the skin texels of :func:`synth.textures.make_albedo` (linear RGB, before the texture is filled and
encoded), what a person shows at the 100-300 px people are seen at, and finer detail for close
views. Make-up-free. Everything is placed in 3D on the rest mesh, so it does not follow UV seams.

The face (its frame, the eyeballs that close Anny's empty eye sockets, eyes, eyebrows, lips, flush
and facial hair) is painted by :mod:`synth.face_detail`; this module paints the rest:

- **skin**: pore-scale and millimetre mottling (value noise), centimetre blotches of redness,
  freckles on sun-exposed skin for some light-skinned people (spots in a 3D grid of 5 mm cells), a
  few moles anywhere;
- **joints and hands**: redder (on dark skin darker) skin over the elbows, knees and knuckles; palms
  lighter than the back of the hand, much lighter for dark skin (the back is found from the thumb:
  the fingertip farthest from the others); light fingernails at the fingertips (the vertices
  farthest from the wrist among their neighbours).

Randomness comes from :func:`sample_detail` with a generator of its own (:func:`detail_rng`), never
the outfit's, so a subject made without detail is the same as before this module.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from blsm.color import srgb_to_linear
from synth.face_detail import FACE_POINTS, LUM, Face, face_features, fit_eyeballs, mix, scale, smoothstep

DETAIL_STREAM = 0x736B696E  # "skin": the random stream of a dataset's subjects' skin detail
BEARDS = ("none", "stubble", "beard", "goatee")
# sRGB of iris colours: dark brown, brown, light brown, hazel, green, blue, grey.
_IRIS_HEX = "2b1a10 4e3220 74502f 7d6a3c 5d7048 5f7f9e 7c8a96"
_HEAD_BONES = ("head", "neck")


def detail_rng(seed: int, subject_id: str) -> np.random.Generator:
    """The generator of a subject's detail in a dataset of seed ``seed`` (independent of the rest)."""
    return np.random.default_rng([int(seed), zlib.crc32(str(subject_id).encode()), DETAIL_STREAM])


def _hex(codes: str) -> np.ndarray:
    rgb = [[int(h[i : i + 2], 16) / 255 for i in (0, 2, 4)] for h in codes.split()]
    return srgb_to_linear(np.array(rgb))


def skin_darkness(skin: np.ndarray) -> float:
    """0 for the lightest skin of :data:`synth.procedural.SKIN_PALETTE`, 1 for the darkest."""
    from synth.procedural import SKIN_PALETTE

    lo, hi = SKIN_PALETTE[-1] @ LUM, SKIN_PALETTE[0] @ LUM
    return float(np.clip((hi - np.asarray(skin) @ LUM) / (hi - lo), 0, 1))


@dataclass(frozen=True)
class SkinDetail:
    """What :func:`paint_detail` paints, and where the face is.

    Attributes:
        face: keypoint name (``FACE_POINTS``) -> (3,) rest position in metres, in the frame of the
            mesh being painted (Y up, facing +Z).
        iris: linear RGB of the irises.
        gaze: (2,) offset of the irises from the openings' centres, units of ``e``.
        brow: eyebrow density in [0, 1]; ``brow_width``: their width at the inner end, units of ``e``.
        lips: linear RGB factor of the lips over the skin.
        flush: redness of nose, cheeks and ears in [0, 1].
        beard: one of ``BEARDS``; ``beard_density`` in [0, 1].
        freckles: freckle density in [0, 1] (0: none); ``moles``: how many moles.
        seed: seeds the noise and the moles' places.
        eyes: ``left_eye`` / ``right_eye`` -> eyeball centre (3 numbers, metres) and radius (metres),
            for each eye with one (:func:`fit_eyeballs`); an eye without is painted on the surface.
    """

    face: dict[str, tuple[float, float, float]]
    iris: tuple[float, float, float]
    gaze: tuple[float, float]
    brow: float
    brow_width: float
    lips: tuple[float, float, float]
    flush: float
    beard: str
    beard_density: float
    freckles: float
    moles: int
    seed: int
    eyes: dict[str, tuple[float, float, float, float]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if set(self.face) != set(FACE_POINTS):
            raise ValueError(f"detail face must have the keypoints {FACE_POINTS}, got {sorted(self.face)}")
        for k, v in self.face.items():
            if np.asarray(v).shape != (3,) or not np.isfinite(v).all():
                raise ValueError(f"detail face[{k!r}] must be 3 finite numbers, got {v!r}")
        if self.beard not in BEARDS:
            raise ValueError(f"detail beard must be one of {BEARDS}, got {self.beard!r}")
        for name in ("brow", "flush", "beard_density", "freckles"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"detail {name} must lie in [0, 1], got {getattr(self, name)}")
        if self.moles < 0:
            raise ValueError(f"detail moles must be >= 0, got {self.moles}")

    def to_json(self) -> dict:
        """The random choices as plain JSON (the face keypoints left out: they follow the mesh)."""
        out = {
            k: getattr(self, k) for k in ("brow", "brow_width", "flush", "beard", "beard_density", "freckles")
        }
        out.update(
            iris=list(self.iris), gaze=list(self.gaze), lips=list(self.lips), moles=self.moles, seed=self.seed
        )
        return out


def sample_detail(
    rng: np.random.Generator, face: dict[str, np.ndarray], skin: Any, hair: Any, phenotype: dict[str, float]
) -> SkinDetail:
    """Draw a person's detail.

    Args:
        rng: the detail's own generator (:func:`detail_rng`).
        face: ``FACE_POINTS`` -> (3,) rest positions, metres.
        skin, hair: linear RGB of the outfit's skin and hair.
        phenotype: Anny's phenotype with ``gender`` (0 male, 1 female) and ``age_years``.

    Returns:
        The detail. Irises darker for darker skin (blue and green only for light skin); facial hair
        for adult men only (``gender`` < 0.5: stubble 35 %, beard 12 %, goatee 6 %); freckles for a
        share of the light-skinned (more with red hair); moles fewer for dark skin.
    """
    dark = skin_darkness(np.asarray(skin))
    male, age = float(phenotype.get("gender", 0.5)) < 0.5, float(phenotype.get("age_years", 30.0))
    w = np.array([1 + 8 * dark, 1 + 2 * dark, 0.6 * (1 - dark), 0.5 * (1 - dark), 0.4 * (1 - dark) ** 2,
                  0.9 * (1 - dark) ** 3, 0.3 * (1 - dark) ** 3])  # fmt: skip
    iris = _hex(_IRIS_HEX)[rng.choice(len(w), p=w / w.sum())] * rng.uniform(0.85, 1.15)
    gaze = rng.normal(0, 0.04, 2)
    brow = rng.uniform(0.75, 1.0) * (1.0 if age >= 14 else 0.7)
    brow_width = rng.uniform(0.2, 0.28) * (1.15 if male else 0.9)
    lips = np.array([0.92, 0.6, 0.64]) * rng.uniform(0.8, 0.97) * rng.uniform(0.95, 1.05, 3)
    lips = lips * (1 - 0.2 * dark) + 0.2 * dark * np.array([0.7, 0.55, 0.6])  # browner on dark skin
    flush = rng.uniform(0.2, 1.0) * (1 - 0.5 * dark)
    beard, density = "none", 0.0
    if male and age >= 18:
        beard = str(rng.choice(BEARDS, p=[0.47, 0.35, 0.12, 0.06]))
        density = rng.uniform(0.4, 0.8) if beard == "stubble" else rng.uniform(0.75, 1.0)
        density = 0.0 if beard == "none" else density
    red_hair = np.asarray(hair)[0] > 1.6 * np.asarray(hair)[2] and np.asarray(hair) @ LUM > 0.03
    p_freckles = max(0.0, 0.45 - dark) * (2.0 if red_hair else 1.0)
    freckles = rng.uniform(0.2, 1.0) if rng.uniform() < p_freckles else 0.0
    moles = int(rng.poisson(12 * (1 - 0.6 * dark) * min(age, 40) / 40))

    def rgb(c) -> tuple[float, float, float]:
        r, g, b = (float(x) for x in np.clip(c, 0.0, 1.0))
        return r, g, b

    return SkinDetail(
        face={k: tuple(float(x) for x in np.asarray(face[k]).reshape(3)) for k in FACE_POINTS},
        iris=rgb(iris), gaze=(float(gaze[0]), float(gaze[1])), brow=float(brow),
        brow_width=float(brow_width), lips=rgb(lips), flush=float(flush), beard=beard,
        beard_density=float(density), freckles=float(freckles), moles=moles, seed=int(rng.integers(2**31)),
    )  # fmt: skip


def subject_detail(
    seed: int,
    subject_id: str,
    vertices: np.ndarray,
    faces: np.ndarray,
    vertex_bones: np.ndarray,
    bone_names: list[str],
    points: dict[str, Any],
    skin: Any,
    hair: Any,
    phenotype: dict[str, float],
) -> tuple[np.ndarray, SkinDetail]:
    """A subject's detail in a dataset of seed ``seed``: its eyeballs fitted (:func:`fit_eyeballs`)
    and its choices drawn from its own generator (:func:`detail_rng`).

    Args:
        vertices: (V, 3) rest mesh, metres; faces (F, 3); vertex_bones (V,) index into ``bone_names``.
        points: ``FACE_POINTS`` -> (3,) rest keypoints, metres; skin, hair: the outfit's colours;
            phenotype: Anny's (``gender``, ``age_years``).

    Returns:
        The vertices with eyeballs and the :class:`SkinDetail` to paint on them.
    """
    import dataclasses

    head = np.isin(vertex_bones, [bone_names.index(b) for b in _HEAD_BONES])
    vertices, eyes = fit_eyeballs(vertices, faces, head, points)
    detail = sample_detail(detail_rng(seed, subject_id), points, skin, hair, phenotype)
    return vertices, dataclasses.replace(detail, eyes=eyes)


# ------------------------------------------------------------------------------------------------
# Painting


def paint_detail(body: Any, faces: np.ndarray, label: np.ndarray, colour: np.ndarray, outfit: Any,
                 detail: SkinDetail) -> np.ndarray:  # fmt: skip
    """Paint ``detail`` into the skin texels of a body (see the module docstring).

    Args:
        body: the texels of :func:`synth.textures.make_albedo` (``synth.textures._Texels``).
        faces: (F, 3) the mesh's triangles.
        label: (N,) the texels' labels (0 skin; only skin is painted).
        colour: (N, 3) their linear RGB.
        outfit: the :class:`synth.textures.Outfit` (skin and hair colours).
        detail: what to paint (:func:`sample_detail`).

    Returns:
        (N, 3) linear RGB, a new array.
    """
    from synth.procedural import value_noise

    colour = np.array(colour, dtype=np.float64)
    skin_rgb, hair_rgb = np.asarray(outfit.skin), np.asarray(outfit.hair)
    dark = skin_darkness(skin_rgb)
    table = np.random.default_rng(detail.seed).uniform(size=4096)
    names = body.bone_names
    head_bones = np.isin(body.vertex_bones, [names.index(b) for b in _HEAD_BONES])
    face = Face.of(detail.face, body.vertices, faces, head_bones)
    skin = label == 0
    _skin_texture(body, colour, skin, table, value_noise)
    _freckles_and_moles(body, colour, skin, detail, face)
    _joints_and_hands(body, faces, colour, skin, face, dark, skin_rgb)
    hm = skin & (body.part <= 1)  # head and neck skin
    sub = colour[hm]
    face_features(body, face, hm, sub, detail, skin_rgb, hair_rgb, table, value_noise)
    colour[hm] = sub
    return colour


def _skin_texture(body: Any, colour: np.ndarray, skin: np.ndarray, table: np.ndarray, noise: Any) -> None:
    """Pores and millimetre mottling (brightness), and centimetre blotches of redness."""
    p = body.p[skin]
    fine = noise(p / 0.0006, table) - 0.5
    mm = noise(p / 0.002 + 3.1, table) - 0.5
    blotch = noise(p / 0.012 + 11.7, table[::-1].copy()) - 0.5
    colour[skin] *= (1 + 0.035 * fine + 0.04 * mm)[:, None]
    colour[skin] *= 1 + np.outer(blotch, [0.02, -0.05, -0.04])


def _cells(p: np.ndarray, size: float, table: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Per point: ``k`` uniforms of its cell of a 3D grid of ``size`` metres (hashed into
    ``table``), and the point's position in its cell in [0, 1)^3."""
    g = p / size
    i = np.floor(g).astype(np.int64)
    h = (i[:, 0] * 73856093) ^ (i[:, 1] * 19349663) ^ (i[:, 2] * 83492791)
    u = np.stack([table[(h * (2 * j + 1) + 977 * j) & (len(table) - 1)] for j in range(k)], 1)
    return u, g - i


def _freckles_and_moles(
    body: Any, colour: np.ndarray, skin: np.ndarray, detail: SkinDetail, face: Face
) -> None:
    """Freckles on sun-exposed skin (one spot at most per 5 mm cell) and ``detail.moles`` moles."""
    rng = np.random.default_rng([detail.seed, 1])
    table = rng.uniform(size=8192)
    if detail.freckles > 0:
        j = body.j
        p = body.p
        exposure = np.select(
            [body.part == 0, body.part == 1, (body.part == 2) & (p[:, 1] > j["spine_03"][1]),
             (body.part == 3) | (body.part == 4)],
            [np.clip(face.coords(p)[:, 2] + 1.5, 0, 1.5), 0.4, 0.6, 0.6], 0.12,
        )  # fmt: skip
        m = skin & (exposure > 0)
        cell = 0.005
        u, f = _cells(p[m], cell, table, 6)
        radius = 0.1 + 0.2 * u[:, 4]  # of the cell: 0.5 to 1.5 mm
        centre = radius[:, None] + (1 - 2 * radius[:, None]) * u[:, 1:4]
        d = np.linalg.norm(f - centre, axis=1)
        soft = np.maximum(body.texel_m[m] / cell, 0.03)
        spot = (u[:, 0] < detail.freckles * 0.7 * exposure[m]) * np.clip((radius - d) / soft + 0.5, 0, 1)
        scale(colour, m, [0.7, 0.56, 0.45], spot * (0.45 + 0.4 * u[:, 5]))
    if detail.moles:
        idx = np.flatnonzero(skin)
        w = body.texel_m[idx] ** 2
        for i in rng.choice(idx, size=detail.moles, p=w / w.sum()):
            r = rng.uniform(0.0008, 0.0022)
            near = np.flatnonzero(skin & (np.abs(body.p - body.p[i]).max(1) < 2 * r))
            d = np.linalg.norm(body.p[near] - body.p[i], axis=1)
            a = np.clip((r - d) / np.maximum(body.texel_m[near], 2e-4) + 0.5, 0, 1) * rng.uniform(0.5, 0.85)
            scale(colour, near, [0.42, 0.33, 0.28], a)


def _fingertips(body: Any, faces: np.ndarray, hand: np.ndarray, wrist: np.ndarray, k: int = 5) -> np.ndarray:
    """Up to ``k`` vertices of the vertex mask ``hand`` farthest from ``wrist`` among their mesh
    neighbours three rings out: (k, 3) fingertip positions, farthest first."""
    from scipy import sparse

    n = len(body.vertices)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = e[hand[e].all(1)]
    adj = sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    adj = ((adj + adj.T + sparse.identity(n)) > 0).astype(np.float64)
    d = np.where(hand, np.linalg.norm(body.vertices - wrist, axis=1), -np.inf)
    best = d.copy()
    rows = adj.tocoo()
    for _ in range(3):  # max over the neighbourhood
        m = np.full(n, -np.inf)
        np.maximum.at(m, rows.row, best[rows.col])
        best = m
    tips = np.flatnonzero(hand & (d >= best) & np.isfinite(d))
    tips = tips[np.argsort(-d[tips])][:k]
    return body.vertices[tips]


def _joints_and_hands(body: Any, faces: np.ndarray, colour: np.ndarray, skin: np.ndarray, face: Face,
                      dark: float, skin_rgb: np.ndarray) -> None:  # fmt: skip
    """Rough skin at elbows, knees and knuckles; lighter palms; fingernails."""
    j, p = body.j, body.p
    nrm = sum(body.bary[:, k, None] * body.vn[body.corners[:, k]] for k in range(3))
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    rough = np.array([0.97, 0.8, 0.8]) * (1 - 0.5 * dark) + np.array([0.8, 0.75, 0.75]) * 0.5 * dark
    unit = body.unit
    fwd = face.rot[2]
    for a, b, c, part, r in (
        ("shoulder", "elbow", "wrist", (3, 4), 0.035),
        ("hip", "knee", "ankle", (5, 6), 0.04),
    ):
        for side, q in (("_l", part[0]), ("_r", part[1])):
            m = skin & (body.part == q)
            if not m.any():
                continue
            pa, pb, pc = j[a + side], j[b + side], j[c + side]
            d1, d2 = (pb - pa) / np.linalg.norm(pb - pa), (pc - pb) / np.linalg.norm(pc - pb)
            out = d1 - d2
            if np.linalg.norm(out) < 0.2:  # a straight limb: the elbow's back, the knee's front
                out = -fwd if a == "shoulder" else fwd
            out = out - (out @ d1) * d1
            out /= np.linalg.norm(out)
            along = (p[m] - pb) @ ((d1 + d2) / np.linalg.norm(d1 + d2))  # along the limb, from the joint
            w = np.exp(-((along / (r * unit)) ** 2)) * smoothstep(-0.2, 0.6, nrm[m] @ out)
            scale(colour, m, rough, 0.8 * w)
    for side, q, sgn in (("_l", 3, 1.0), ("_r", 4, -1.0)):
        wrist, elbow = j["wrist" + side], j["elbow" + side]
        axis = (wrist - elbow) / np.linalg.norm(wrist - elbow)
        hand_v = (body.vertex_bones == body.bone_names.index("wrist" + side)) & (
            (body.vertices - wrist) @ axis > 0
        )
        m = skin & (body.part == q) & ((p - wrist) @ axis > -0.01 * unit)
        if hand_v.sum() < 20 or not m.any():
            continue
        tips = _fingertips(body, faces, hand_v, wrist)
        if len(tips) < 5:
            continue
        k = int(np.linalg.norm(tips[:, None] - tips[None], axis=2).mean(1).argmax())  # the thumb stands apart
        thumb, fingers = tips[k], np.delete(tips, k, 0)
        hand_axis = fingers.mean(0) - wrist
        hand_axis /= np.linalg.norm(hand_axis)
        length = float(np.max((fingers - wrist) @ hand_axis))
        radial = (thumb - wrist) - ((thumb - wrist) @ hand_axis) * hand_axis
        if np.linalg.norm(radial) < 1e-6:
            continue
        radial /= np.linalg.norm(radial)
        dorsal = -sgn * np.cross(hand_axis, radial)  # the back of the hand (the palm: thumb side, by hand)
        t = (p[m] - wrist) @ hand_axis / length  # 0 at the wrist, 1 at the longest fingertip
        nd = nrm[m] @ dorsal
        palm = np.clip(skin_rgb * 1.15 + 0.5 * (np.array([0.5, 0.36, 0.3]) - skin_rgb), 0.02, 0.7)
        mix(colour, m, palm, (0.25 + 0.5 * dark) * smoothstep(0.0, -0.5, nd) * smoothstep(-0.05, 0.1, t))
        knuckles = np.exp(-(((t - 0.53) / 0.04) ** 2)) + 0.8 * np.exp(-(((t - 0.74) / 0.035) ** 2))
        scale(colour, m, rough, 0.7 * knuckles * smoothstep(0.1, 0.6, nd))
        nail, edge = np.zeros(m.sum()), np.zeros(m.sum())
        r = 0.065 * length
        for i, tip in enumerate(tips):
            up = dorsal if i != k else (radial + 0.5 * dorsal) / np.linalg.norm(radial + 0.5 * dorsal)
            d = np.linalg.norm(p[m] - tip, axis=1)
            a = smoothstep(r, 0.75 * r, d) * smoothstep(0.25, 0.55, nrm[m] @ up)
            nail, edge = np.maximum(nail, a), np.maximum(edge, a * smoothstep(0.35 * r, 0.2 * r, d))
        pink = np.clip(skin_rgb * 1.1 + 0.35 * (np.array([0.62, 0.48, 0.45]) - skin_rgb), 0, 0.8)
        mix(colour, m, pink, 0.8 * nail)
        mix(colour, m, np.array([0.7, 0.66, 0.62]), 0.6 * edge)
