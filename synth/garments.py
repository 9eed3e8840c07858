"""Clothing geometry for the stand-in people: garments as meshes over the body, skinned with it.

The painted outfit (:mod:`synth.textures`) says where each garment is; on its own it is a coat of
paint, and a network trained on painted people learns that a body's outline is the skin's. Real
people wear cloth that stands off the body: loose shirts, jackets, wide trousers, skirts. This
module gives every garment of the painted outfit a surface of its own, in two meshes per person:

- **the cloth layer**: a copy of the body's mesh (the same topology, UV layout and texture, so one
  renderer serves every subject and the fabric shows the painted colours and patterns), each vertex
  pushed along the rest body's normal by the garment's thickness where the paint says a garment
  is (:func:`synth.textures.vertex_labels`, from the borders the paint drew,
  ``meta["outfit_cuts"]`` of the subject) and sunk ``INSET`` under the skin elsewhere, where the
  body hides it. The faces across a border slant from the cloth into the skin: the garment's hem.
  Thickness per garment (:class:`GarmentSpec`): a base over the whole garment; **ease** that grows
  towards the hem of a top (a shirt hangs from the chest, it does not follow the waist) and of a
  sleeve, and down a trouser leg; a thicker, stiffer layer for a **jacket** (a long-sleeved top);
  thicker shoes. The displaced layer is then draped: smoothed over the body's hollows (between the
  shoulder blades, under the chest) and held at least the base thickness off the skin, and given
  **folds** (value noise of the rest position along the normal, stronger at the elbows, the
  back of the knees and the waist).
- **the skirt**: skirts and dresses cannot be a layer of the legs: the cloth spans the gap between
  them. A tube of ``RINGS`` x ``SEGMENTS`` vertices (the same topology for everyone; hidden when the
  outfit has none) hangs from the waist to the hem: each ring at least as wide as the body at its
  height and at every height above it, plus an A-line flare towards the hem. A dress is a longer
  skirt in the top's colour, so that the top and the skirt read as one garment.

**Skinning.** The layer's vertex takes the body vertex's weights, so the posed cloth is the posed
body plus the blended rotation of its offset: it follows every pose exactly as the skin does. A
skirt vertex takes the weights of the nearest body vertex of the pelvis, spine and thighs,
smoothed around each ring and down the skirt (the rings' weights blend the two thighs at the front
and back), the waist ring kept on the body's. Cloth is not simulated: a skirt keeps its rest shape
about the legs (a long stride or a raised knee can push a leg through it), a loose shirt does not
fall when the arms rise, and cloth does not collide with other limbs.

**Labels** stay those of the body underneath (BEDLAM's rule): keypoints, joints, BLSM parameters
and vertices are the body's. The mask and the parts include the clothes: a pixel on the layer
belongs to its person and to the bone of the body face under it (layer face ``f`` lies over body
face ``f``); a pixel on the skirt to the bone of the skirt face's largest weight (the pelvis or a
thigh). Cloth is the person's surface for keypoint visibility (a clothed elbow is visible, as
annotators of photographs mark it), unlike hair, which hides the surface keypoints under it. In the
correspondence label (``corr``), faces are numbered body, hair, layer, skirt
(:mod:`synth.dataset.format`); ``synth validate`` rebuilds all four from the subject and the sample's
``garments`` spec.

Everything is a function of the subject and the :class:`GarmentSpec`, whose ``seed`` fixes the
random choices; the sample's JSON stores the spec (:func:`subject_garments` rebuilds the mesh).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

GARMENT_STREAM = 0x636C6F74  # "clot": the random stream of the garments of a dataset's subjects
FITS = ("fitted", "regular", "loose")
INSET = 0.002  # metres: the layer under the skin where no garment is
RINGS, SEGMENTS = 24, 72  # the skirt's tube
# Per fit: (base thickness, ease at a top's hem, ease at a trouser leg's hem), metres, each drawn
# uniformly in its range.
BASE = {"fitted": (0.003, 0.006), "regular": (0.005, 0.01), "loose": (0.008, 0.015)}
TOP_EASE = {"fitted": (0.0, 0.01), "regular": (0.01, 0.03), "loose": (0.03, 0.06)}
LEG_EASE = {"fitted": (0.0, 0.008), "regular": (0.008, 0.02), "loose": (0.02, 0.05)}
JACKET = (0.015, 0.03)  # a jacket's base thickness
SHOE = (0.004, 0.01)
FOLD = (0.001, 0.004)  # fold amplitude
SKIRT_FLARE = (0.03, 0.15)  # metres added to the radius at the hem
DRESS_LENGTH = (1.15, 1.6)  # a dress's hem along hip -> knee (1 = the knee)
_PARTS_SKIRT = ("pelvis", "spine_01", "hip_l", "hip_r", "knee_l", "knee_r")


@dataclass(frozen=True)
class GarmentSpec:
    """One person's garments (JSON-able: the sample's ``people[i].garments``).

    Attributes:
        fit: one of ``FITS``.
        base: the cloth's thickness over the skin, metres (the top's; ``jacket`` replaces it).
        top_ease, leg_ease: extra standing-off at a top's hem and at a trouser leg's hem, metres.
        jacket: the long-sleeved top is a jacket, ``jacket`` metres thick (0: not a jacket).
        shoe: the shoes' thickness, metres.
        fold: the folds' amplitude, metres.
        skirt: "" (none), "skirt" or "dress".
        flare: the skirt's extra radius at the hem, metres; ``length`` its hem along hip -> knee.
        seed: the seed of the folds' noise.
    """

    fit: str
    base: float
    top_ease: float
    leg_ease: float
    jacket: float
    shoe: float
    fold: float
    skirt: str
    flare: float
    length: float
    seed: int

    def __post_init__(self) -> None:
        if self.fit not in FITS:
            raise ValueError(f"garment fit must be one of {', '.join(FITS)}, got {self.fit!r}")
        if self.skirt not in ("", "skirt", "dress"):
            raise ValueError(f"garment skirt must be '', 'skirt' or 'dress', got {self.skirt!r}")
        sizes = (self.base, self.top_ease, self.leg_ease, self.jacket, self.shoe, self.fold, self.flare)
        if not all(0 <= s < 0.2 for s in sizes) or not 0.3 <= self.length <= 2.5:
            raise ValueError(f"garment sizes must lie in [0, 0.2) m and length in [0.3, 2.5]: {self}")

    def to_json(self) -> dict[str, Any]:
        out = {k: (round(v, 6) if isinstance(v, float) else v) for k, v in self.__dict__.items()}
        out["seed"] = int(self.seed)
        return out

    @staticmethod
    def from_json(d: dict[str, Any]) -> GarmentSpec:
        try:
            return GarmentSpec(
                fit=str(d["fit"]), base=float(d["base"]), top_ease=float(d["top_ease"]),
                leg_ease=float(d["leg_ease"]), jacket=float(d["jacket"]), shoe=float(d["shoe"]),
                fold=float(d["fold"]), skirt=str(d["skirt"]), flare=float(d["flare"]),
                length=float(d["length"]), seed=int(d["seed"]),
            )  # fmt: skip
        except (KeyError, TypeError) as exc:
            raise ValueError(f"garment spec lacks or mistypes {exc}") from None


def sample_garments(rng: np.random.Generator, outfit: Any, fits: dict[str, float], jacket: float,
                    dress: float) -> GarmentSpec:
    """Draw the garments of ``outfit`` (:class:`synth.textures.Outfit`): the fit by the weights
    ``fits``, sizes uniformly in the fit's ranges, a long-sleeved top a jacket with probability
    ``jacket``, a skirt a dress with probability ``dress``. Rounded as stored."""
    names = [f for f in FITS if fits.get(f, 0.0) > 0]
    if not names:
        raise ValueError("garments.fits: at least one fit needs a positive weight")
    w = np.array([fits[f] for f in names], np.float64)
    fit = names[int(rng.choice(len(names), p=w / w.sum()))]
    base, top_ease, leg_ease = (float(rng.uniform(*t[fit])) for t in (BASE, TOP_EASE, LEG_EASE))
    is_jacket = outfit.top == "longsleeve" and rng.uniform() < jacket
    jk = float(rng.uniform(*JACKET)) if is_jacket else 0.0
    shoe, fold, flare = float(rng.uniform(*SHOE)), float(rng.uniform(*FOLD)), float(rng.uniform(*SKIRT_FLARE))
    skirt = ""
    length = 1.0
    if outfit.bottoms == "skirt":
        skirt = "dress" if rng.uniform() < dress else "skirt"
        length = float(rng.uniform(*DRESS_LENGTH)) if skirt == "dress" else float(rng.uniform(0.85, 1.05))
    spec = GarmentSpec(fit, base, top_ease, leg_ease, jk, shoe, fold, skirt, flare, length, int(rng.integers(2**31)))
    return GarmentSpec.from_json(spec.to_json())


@dataclass(frozen=True)
class GarmentMesh:
    """A person's garments in the rest frame.

    Attributes:
        layer: (V, 3) float32 the cloth layer (the body's topology and weights).
        label: (V,) the paint's label of each body vertex (:func:`synth.textures.vertex_labels`).
        skirt: (S, 3) float32 the skirt's vertices (:func:`skirt_faces`), or None.
        skirt_weights: (S, J) its LBS weights; ``skirt_colours`` (S, 3) linear RGB;
            ``skirt_face_bones`` (Fs,) each skirt face's bone (:func:`synth.labels.face_bones`);
            all three or None.
    """

    layer: np.ndarray
    label: np.ndarray
    skirt: np.ndarray | None
    skirt_weights: np.ndarray | None
    skirt_colours: np.ndarray | None
    skirt_face_bones: np.ndarray | None = None


@lru_cache(maxsize=1)
def skirt_faces() -> np.ndarray:
    """(F, 3) int32 faces of every skirt tube (ring ``r``, segment ``s`` is vertex ``r * SEGMENTS + s``;
    outward winding)."""
    r, s = np.meshgrid(np.arange(RINGS - 1), np.arange(SEGMENTS), indexing="ij")
    a, b = r * SEGMENTS + s, r * SEGMENTS + (s + 1) % SEGMENTS
    c, d = a + SEGMENTS, b + SEGMENTS
    faces = np.stack([np.stack([a, c, b], -1), np.stack([b, c, d], -1)], -2).reshape(-1, 3).astype(np.int32)
    faces.setflags(write=False)
    return faces


def skirt_vertex_count() -> int:
    return RINGS * SEGMENTS


def _noise(p: np.ndarray, seed: int) -> np.ndarray:
    """Smooth value noise in [-1, 1] of points (N, 3) on the unit lattice."""
    from synth.procedural import value_noise

    table = np.random.default_rng(seed).uniform(size=4096)
    return 2.0 * value_noise(p, table) - 1.0


def build_garments(
    template: np.ndarray,
    faces: np.ndarray,
    weights: np.ndarray,
    label: np.ndarray,
    bone_names: list[str],
    joints: np.ndarray,
    colours: dict[str, Any],
    spec: GarmentSpec,
) -> GarmentMesh:
    """Dress a rest body (see the module docstring).

    Args:
        template: (V, 3) the body in the rest frame (Y up, facing +Z), metres.
        faces: (F, 3) its faces (outward winding); ``weights`` (V, J) its LBS weights.
        label: (V,) each vertex's painted label: 0 skin, 1 top, 2 bottoms, 3 shoes, 4 soles, 5 hair.
        bone_names, joints: (J,) names and (J, 3) rest positions of the bone heads.
        colours: the outfit's linear RGB by key ("top", "bottoms", ...): the skirt's colour.
        spec: the garments.
    """
    from blsm.mesh import vertex_normals

    v = np.asarray(template, np.float64)
    n = vertex_normals(v, np.asarray(faces, np.int64))
    j = {name: np.asarray(joints[i], np.float64) for i, name in enumerate(bone_names)}
    vb = np.asarray(weights).argmax(1)
    d = _thickness(v, vb, label, bone_names, j, spec)
    faces = np.asarray(faces, np.int64)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    cloth = d > 0
    # The hem: cloth vertices next to skin lie on the skin, so the faces out to the skin are painted
    # cloth and the cloth tapers to its edge (a face from cloth to the sunk layer shows skin paint).
    border = np.zeros(len(v), bool)
    for a, b in ((0, 1), (1, 0)):
        border[e[cloth[e[:, a]] & ~cloth[e[:, b]], a]] = True
    d[border] = 0.0
    layer = v + d[:, None] * n
    layer = _drape(layer, v, n, e, cloth & ~border, cloth, d)
    cloth &= ~border
    # Folds: along the normal, stronger where the body bends.
    bend = np.zeros(len(v))
    for name in ("elbow_l", "elbow_r", "knee_l", "knee_r", "pelvis"):
        bend = np.maximum(bend, np.exp(-(np.linalg.norm(v - j[name], axis=1) / 0.08) ** 2))
    fold = spec.fold * (0.6 + 1.4 * bend) * _noise(v * np.array([18.0, 9.0, 18.0]), spec.seed)
    layer[cloth] += (fold[cloth])[:, None] * n[cloth]
    layer[~cloth & ~border] = v[~cloth & ~border] - INSET * n[~cloth & ~border]
    layer[border] = v[border]
    floor = v[:, 1].min()
    layer[:, 1] = np.maximum(layer[:, 1], np.where(cloth, floor, -np.inf))  # shoes do not sink
    sk = sw = sc = None
    if spec.skirt:
        sk, sw = _skirt(v, np.asarray(weights, np.float64), vb, bone_names, j, spec)
        key = "top" if spec.skirt == "dress" else "bottoms"
        grain = 1.0 + 0.05 * _noise(sk / 0.01, spec.seed + 1)
        sc = np.clip(np.asarray(colours[key], np.float64)[None] * grain[:, None], 0.0, 1.0)
    return GarmentMesh(
        layer=layer.astype(np.float32), label=np.asarray(label, np.int8),
        # synth.labels.face_bones's rule (not imported: labels -> render -> garments)
        skirt_face_bones=None if sw is None else sw.astype(np.float32)[skirt_faces()].sum(1).argmax(1),
        skirt=None if sk is None else sk.astype(np.float32), skirt_weights=None if sw is None else sw.astype(np.float32),
        skirt_colours=None if sc is None else sc.astype(np.float32),
    )  # fmt: skip


def _thickness(v, vb, label, bone_names, j, spec: GarmentSpec) -> np.ndarray:
    """(V,) the cloth's distance off the skin: 0 where no garment is (the docstring's profile)."""
    bi = {b: i for i, b in enumerate(bone_names)}
    y = v[:, 1]
    d = np.zeros(len(v))
    arm = np.isin(vb, [bi[b] for b in ("shoulder_l", "elbow_l", "wrist_l", "shoulder_r", "elbow_r", "wrist_r")])
    leg = np.isin(vb, [bi[b] for b in ("hip_l", "knee_l", "ankle_l", "hip_r", "knee_r", "ankle_r")])
    # Top: the ease grows from the chest (the armpits' height) down to the top's lowest point, and
    # along a sleeve from the shoulder to its cuff.
    top = label == 1
    if top.any():
        y_chest = 0.5 * (j["spine_03"][1] + j["shoulder_l"][1])
        y_hem = y[top & ~arm].min() if (top & ~arm).any() else j["pelvis"][1]
        down = np.clip((y_chest - y) / max(y_chest - y_hem, 1e-3), 0, 1)
        along = _along_limb(v, arm, j, "shoulder", "wrist")
        base = spec.jacket if spec.jacket > 0 else spec.base
        ease = np.where(arm, 0.6 * along, down**1.5)
        d[top] = base + spec.top_ease * ease[top]
    bottoms = label == 2
    if bottoms.any():
        down = _along_limb(v, leg, j, "hip", "ankle")
        d[bottoms] = spec.base + spec.leg_ease * (0.3 + 0.7 * down[bottoms])
        if spec.skirt:  # under a skirt the legs' paint is the skirt's: no layer there
            d[bottoms & leg] = 0.0
    shoes = (label == 3) | (label == 4)
    d[shoes] = spec.shoe
    return d


def _along_limb(v: np.ndarray, limb: np.ndarray, j: dict[str, np.ndarray], a: str, b: str) -> np.ndarray:
    """(V,) each ``limb`` vertex's fraction (clipped to [0, 1]) along joint ``a`` -> ``b`` of its
    side (``_l`` or ``_r`` by the side of the pelvis it is on); 0 elsewhere."""
    out = np.zeros(len(v))
    for side in ("_l", "_r"):
        p, q = j[a + side], j[b + side]
        t = (v - p) @ (q - p) / ((q - p) @ (q - p))
        m = limb & (np.sign(v[:, 0] - j["pelvis"][0]) == np.sign(p[0] - j["pelvis"][0]))
        out[m] = np.clip(t[m], 0, 1)
    return out


def _drape(layer, v, n, e, move, cloth, d, iterations: int = 12) -> np.ndarray:
    """Smooth the cloth over the body's hollows (umbrella operator over the edges ``e`` between
    ``cloth`` vertices, moving the ``move`` ones), then hold every moved vertex at least 70 % of its
    thickness off the skin along the normal."""
    import scipy.sparse as sp

    e = e[cloth[e[:, 0]] & cloth[e[:, 1]]]
    nv = len(v)
    a = sp.csr_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(nv, nv))
    a.data[:] = 1.0
    deg = np.asarray(a.sum(1)).ravel()
    move = move & (deg > 0)
    out = layer.copy()
    for _ in range(iterations):
        avg = (a @ out) / np.maximum(deg, 1)[:, None]
        out[move] = 0.5 * out[move] + 0.5 * avg[move]
        off = ((out - v) * n).sum(1)
        push = np.maximum(0.7 * d - off, 0.0) * move
        out += push[:, None] * n
    return out


def _skirt(v, weights, vb, bone_names, j, spec: GarmentSpec) -> tuple[np.ndarray, np.ndarray]:
    """The skirt tube (S, 3) in the rest frame and its (S, J) weights (the docstring's rules)."""
    from scipy.spatial import cKDTree

    bi = {b: i for i, b in enumerate(bone_names)}
    region = np.isin(vb, [bi[b] for b in _PARTS_SKIRT])
    c = j["pelvis"]
    y_waist = c[1] + 0.6 * (j["spine_01"][1] - c[1])
    knee = 0.5 * (j["knee_l"][1] + j["knee_r"][1])
    hip = 0.5 * (j["hip_l"][1] + j["hip_r"][1])
    y_hem = hip + spec.length * (knee - hip)
    ys = np.linspace(y_waist, y_hem, RINGS)
    theta = 2 * math.pi * np.arange(SEGMENTS) / SEGMENTS
    dirs = np.stack([np.sin(theta), np.cos(theta)], 1)  # (S, 2) in x, z: 0 is the front (+Z)
    arms = [bi[b] for b in bone_names if b.startswith(("shoulder", "elbow", "wrist", "hand", "finger", "thumb"))]
    p = v[~np.isin(vb, arms)]  # the body's extent at each height: everything but the arms
    rel = p[:, [0, 2]] - c[[0, 2]]
    ang = np.mod(np.arctan2(rel[:, 0], rel[:, 1]), 2 * math.pi)
    rad = np.linalg.norm(rel, axis=1)
    seg = np.floor(ang / (2 * math.pi) * SEGMENTS).astype(np.int64) % SEGMENTS
    radius = np.zeros((RINGS, SEGMENTS))
    band = 0.5 * abs(ys[1] - ys[0]) + 0.01
    for r, y in enumerate(ys):
        m = np.abs(p[:, 1] - y) < band
        ext = np.zeros(SEGMENTS)
        np.maximum.at(ext, seg[m], rad[m])
        for _ in range(4):  # fill empty bins from their neighbours (a bin the legs' gap leaves empty)
            ext = np.where(ext > 0, ext, np.maximum(np.roll(ext, 1), np.roll(ext, -1)))
        ext = np.maximum(ext, np.maximum(np.roll(ext, 1), np.roll(ext, -1)))  # a vertex can lie between bins
        radius[r] = ext if r == 0 else np.maximum(ext, radius[r - 1])  # never narrower than above
    t = np.linspace(0.0, 1.0, RINGS)[:, None]
    radius = radius + 0.004 + spec.base * t + spec.flare * t**1.3
    pts = np.concatenate([c[None, None, [0]] + radius[..., None] * dirs[None, :, :1],
                          np.broadcast_to(ys[:, None, None], (RINGS, SEGMENTS, 1)),
                          c[None, None, [2]] + radius[..., None] * dirs[None, :, 1:]], -1)  # fmt: skip
    pts = pts.reshape(-1, 3)
    idx = np.flatnonzero(region)
    near = idx[cKDTree(v[idx]).query(pts)[1]]
    w = weights[near].reshape(RINGS, SEGMENTS, -1)
    top = w[0].copy()
    for _ in range(40):  # smooth around the rings and down the skirt; the waist ring stays on the body
        w = (2 * w + np.roll(w, 1, 1) + np.roll(w, -1, 1) + np.concatenate([w[:1], w[:-1]]) + np.concatenate([w[1:], w[-1:]])) / 6
        w[0] = top
    w /= w.sum(-1, keepdims=True)
    return pts, w.reshape(RINGS * SEGMENTS, -1)


def pose_garments(garments: GarmentMesh, weights: np.ndarray, transforms: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """(V, 3) float32 posed layer (with the body's ``weights``) and (S, 3) posed skirt (or None):
    LBS with the body's (J, 3, 4) skinning transforms."""
    import torch

    from blsm.lbs import linear_blend_skinning

    tr = torch.as_tensor(np.asarray(transforms), dtype=torch.float32)[None]

    def lbs(x, w):
        out = linear_blend_skinning(torch.as_tensor(x)[None], torch.as_tensor(np.asarray(w, np.float32)), tr[..., :3], tr[..., 3])
        return out[0].numpy().astype(np.float32)

    layer = lbs(garments.layer, weights)
    skirt = None if garments.skirt is None else lbs(garments.skirt, garments.skirt_weights)
    return layer, skirt


def subject_garment_spec(subject: Any, seed: int, fits: dict[str, float], jacket: float, dress: float) -> GarmentSpec:
    """The garments of ``subject`` in a dataset of seed ``seed``: drawn from a generator seeded by
    the dataset seed and the subject's id (so they do not depend on which worker draws them)."""
    from synth.textures import outfit_from_json

    outfit = outfit_from_json(_outfit_json(subject))
    rng = np.random.default_rng([int(seed), zlib.crc32(str(subject.id).encode()), GARMENT_STREAM])
    return sample_garments(rng, outfit, fits, jacket, dress)


def _outfit_json(subject: Any) -> dict[str, Any]:
    meta = subject.meta
    if "outfit" not in meta or "outfit_cuts" not in meta:
        raise ValueError(f"subject {subject.id}: made before garment geometry (its file has no outfit "
                         "borders, meta.outfit_cuts): make the subjects again (a new --out)")
    return meta["outfit"]


def subject_garments(subject: Any, model: Any, spec: GarmentSpec) -> GarmentMesh:
    """Dress the subject's rigged template (``rigged`` pipeline; Anny's people): the paint's labels at
    the scan's vertices (the pose the paint was drawn in), the cloth built on the template."""
    import torch

    from synth.subjects import registration_output
    from synth.textures import outfit_from_json, vertex_labels

    outfit = outfit_from_json(_outfit_json(subject))
    names = list(model.bone_names)
    with torch.no_grad():
        _, _, out = registration_output(model, subject.registration)
    label = vertex_labels(subject.vertices, subject.weights.argmax(1), names, out.joints[0].numpy(), outfit,
                          subject.meta["outfit_cuts"])  # fmt: skip
    return build_garments(subject.template, subject.faces, subject.weights, label, names,
                          out.rest_joints[0].numpy(), outfit.colors, spec)  # fmt: skip
