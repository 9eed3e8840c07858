"""Procedural albedo textures for synthetic people: skin, hair and everyday clothing in UV space.

:func:`sample_outfit` draws an :class:`Outfit` (skin tone, garment types, colours, patterns, hair
colour); :func:`make_albedo` paints it into the texture of a body mesh with a UV layout (Anny's).
Garments are decided in 3D, so their borders do not follow UV seams:

1. Every UV triangle is rasterised (texel centres, barycentric); each covered texel gets its 3D rest
   position and body part (head, neck, torso, arms, legs: the largest interpolated one-hot part of its
   triangle's corners, from the vertices' dominant bones). Uncovered texels copy the nearest covered
   texel, so bilinear filtering at island borders shows no black seams.
2. Garment regions from position and part: sleeve cuffs and leg hems are planes perpendicular to a
   limb bone (projection onto the segment from its joint to the child joint), so they are straight
   rings; the waist, top hem, neckline, tank-top armholes, shoe line and hairline are simple surfaces
   placed relative to the joints.
3. Patterns are solid textures of the 3D position (seamless): stripes along Y; gingham checks and
   staggered dots on the coordinate plane facing the surface normal's dominant axis (they change
   plane along curves, like a garment's seams); heather (value noise). Stripes and checks are
   box-filtered over the texel footprint. Skin varies by +-3 % at low frequency.

Colours are linear RGB albedos; the texture is sRGB uint8 with row 0 at v = 1 (OBJ/OpenGL
convention, which Mitsuba's ``obj`` loader reads as is; with ``ply`` or ``mi.Mesh`` texcoords pass
(u, 1 - v), as Mitsuba puts v = 0 at the top row of a bitmap).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage

from blsm.color import linear_to_srgb, srgb_to_linear
from synth.procedural import SKIN_PALETTE, value_noise
from synth.raster import rasterise_uv, uv_triangles

if TYPE_CHECKING:
    from synth.skin_detail import SkinDetail

TOPS = ("tshirt", "longsleeve", "tank")
BOTTOMS = ("trousers", "shorts", "skirt", "capris")
SHOES = ("shoes", "barefoot")
PATTERNS = ("plain", "stripes", "checks", "dots", "heather")
COLOR_KEYS = ("top", "top_alt", "bottoms", "bottoms_alt", "shoes", "soles")
# Body parts (head, neck, torso, left arm, right arm, left leg, right leg) by BLSM bone.
PARTS = (
    ("head",), ("neck",), ("pelvis", "spine_01", "spine_02", "spine_03", "clavicle_l", "clavicle_r"),
    ("shoulder_l", "elbow_l", "wrist_l"), ("shoulder_r", "elbow_r", "wrist_r"),
    ("hip_l", "knee_l", "ankle_l"), ("hip_r", "knee_r", "ankle_r"),
)  # fmt: skip
# Leg hems: (bone head, bone tail, range of the hem's fraction along that bone).
HEMS = {"shorts": ("hip", "knee", 0.3, 0.6), "skirt": ("hip", "knee", 0.85, 1.05),
        "capris": ("knee", "ankle", 0.45, 0.7), "trousers": ("knee", "ankle", 0.88, 1.0)}  # fmt: skip
_HEX = {  # sRGB of everyday colours: navy, grey, charcoal, black, white, burgundy, ...
    "tops": "1f2a44 8a8d91 36393d 161616 e8e8e4 6d1f2f 2f4f3a 6b6b3a c3b091 b22222 d4a017 3e7c8c "
    "f2d7d0 9bb7d4 5b3a6b d8c8a8 e07a2f",
    "bottoms": "3b5a80 27364f 7d9bbf 161616 36393d c3b091 d8c8a8 1f2a44 6b6b3a 8a8d91 5a3d2b",
    "shoes": "161616 161616 e8e8e4 e8e8e4 5a3d2b 8a8d91 1f2a44 a57a52",
    "soles": "e8e8e4 161616 8f5e2e",
    "hair": "0d0b0a 2b1d14 4a3222 6e4e33 9c7a4f c9a66b 7b3a1e 8c8c8c d6d2cc",
}


def _palette(name: str) -> np.ndarray:
    rgb = [[int(h[i : i + 2], 16) / 255 for i in (0, 2, 4)] for h in _HEX[name].split()]
    return srgb_to_linear(np.array(rgb))


def _rgb(c: np.ndarray) -> tuple[float, float, float]:
    r, g, b = (float(x) for x in np.clip(c, 0.02, 0.85))
    return r, g, b


@dataclass(frozen=True)
class Outfit:
    """What a synthetic person wears.

    Attributes:
        skin: linear RGB skin albedo, channels in [0.02, 0.7].
        top: one of ``TOPS``: "tshirt", "longsleeve", "tank".
        bottoms: one of ``BOTTOMS``: "trousers", "shorts" (mid-thigh), "skirt" (knee length, painted
            on the legs), "capris" (mid-shin).
        shoes: one of ``SHOES``: "shoes", "barefoot".
        colors: linear RGB in [0.02, 0.85] for each of ``COLOR_KEYS``: "top", "top_alt", "bottoms",
            "bottoms_alt", "shoes", "soles"; a pattern's second colour is the garment's "_alt" one.
        patterns: one of ``PATTERNS`` for each of "top", "bottoms", "shoes".
        hair: linear RGB of the hair cap on the top and back of the head.
    """

    skin: tuple[float, float, float]
    top: str
    bottoms: str
    shoes: str
    colors: dict[str, tuple[float, float, float]]
    patterns: dict[str, str]
    hair: tuple[float, float, float]

    def __post_init__(self) -> None:
        for name, allowed in (("top", TOPS), ("bottoms", BOTTOMS), ("shoes", SHOES)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"outfit {name} must be one of {allowed}, got {getattr(self, name)!r}")
        if set(self.colors) != set(COLOR_KEYS):
            raise ValueError(f"outfit colors must have the keys {COLOR_KEYS}, got {sorted(self.colors)}")
        if set(self.patterns) != {"top", "bottoms", "shoes"} or set(self.patterns.values()) - set(PATTERNS):
            raise ValueError(f"outfit patterns must map top, bottoms, shoes to {PATTERNS}: {self.patterns}")

    def to_json(self) -> dict:
        """A plain JSON-able dict (colours as lists of 3 floats; :func:`outfit_from_json` reads it)."""
        out = {k: getattr(self, k) for k in ("top", "bottoms", "shoes")}
        out.update(skin=list(self.skin), hair=list(self.hair), patterns=dict(self.patterns))
        out["colors"] = {k: list(v) for k, v in self.colors.items()}
        return out


def outfit_from_json(d: dict) -> Outfit:
    """The :class:`Outfit` of :meth:`Outfit.to_json` (a subject's ``meta["outfit"]``)."""
    try:
        return Outfit(
            skin=_rgb(np.asarray(d["skin"])), top=str(d["top"]), bottoms=str(d["bottoms"]), shoes=str(d["shoes"]),
            colors={k: _rgb(np.asarray(v)) for k, v in d["colors"].items()}, patterns=dict(d["patterns"]),
            hair=_rgb(np.asarray(d["hair"])),
        )  # fmt: skip
    except (KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"outfit lacks or mistypes {exc}") from None


def _garment_colour(rng: np.random.Generator, palette: str, p_random: float) -> np.ndarray:
    if rng.uniform() < p_random:  # a random saturated colour (HSV, in sRGB)
        h, s, v = rng.uniform(), rng.uniform(0.45, 0.95), rng.uniform(0.35, 0.95)
        rgb = np.clip(np.abs((h * 6 + np.array([0.0, 4.0, 2.0])) % 6 - 3) - 1, 0, 1)
        return srgb_to_linear(v * (1 - s + s * rgb))
    pal = _palette(palette)
    return pal[rng.integers(len(pal))] * rng.uniform(0.92, 1.08, 3)


def _alt_colour(rng: np.random.Generator, base: np.ndarray) -> np.ndarray:
    alt = _garment_colour(rng, "tops", 0.5) if rng.uniform() < 0.5 else np.full(3, rng.choice([0.01, 0.85]))
    lum = np.array([0.2126, 0.7152, 0.0722])
    if abs((linear_to_srgb(alt) - linear_to_srgb(base)) @ lum) < 0.25:  # keep some contrast
        alt = np.full(3, 0.02 if linear_to_srgb(base) @ lum > 0.5 else 0.8)
    return alt


def sample_outfit(rng: np.random.Generator) -> Outfit:
    """Draw a skin tone and an everyday outfit.

    Args:
        rng: the random generator (the only source of randomness).

    Returns:
        The outfit. Skin tones are uniform along ``SKIN_PALETTE`` (very light to very dark) with a
        +-5 % jitter per channel; garment colours mix muted everyday colours and random saturated ones;
        darker skin makes black or dark brown hair likelier.
    """
    t = rng.uniform() * (len(SKIN_PALETTE) - 1)
    i = min(int(t), len(SKIN_PALETTE) - 2)
    skin = SKIN_PALETTE[i] + (t - i) * (SKIN_PALETTE[i + 1] - SKIN_PALETTE[i])
    skin = np.clip(skin * rng.uniform(0.95, 1.05, 3), 0.02, 0.7)
    top = str(rng.choice(TOPS, p=[0.45, 0.35, 0.2]))
    bottoms = str(rng.choice(BOTTOMS, p=[0.5, 0.25, 0.12, 0.13]))
    shoes = str(rng.choice(SHOES, p=[0.93, 0.07]))
    colors = {"top": _garment_colour(rng, "tops", 0.35)}
    colors["top_alt"] = _alt_colour(rng, colors["top"])
    colors["bottoms"] = _garment_colour(rng, "bottoms", 0.4 if bottoms == "skirt" else 0.12)
    colors["bottoms_alt"] = _alt_colour(rng, colors["bottoms"])
    colors["shoes"] = _garment_colour(rng, "shoes", 0.15)
    colors["soles"] = _garment_colour(rng, "soles", 0.0) if rng.uniform() < 0.7 else colors["shoes"]
    patterns = {
        "top": str(rng.choice(PATTERNS, p=[0.4, 0.18, 0.12, 0.1, 0.2])),
        "bottoms": str(rng.choice(PATTERNS, p=[0.5, 0.06, 0.08, 0.04, 0.32])),
        "shoes": str(rng.choice(("plain", "heather"), p=[0.8, 0.2])),
    }
    dark = t / (len(SKIN_PALETTE) - 1)
    w = np.array([1 + 6 * dark, 1 + 3 * dark] + [(1 - dark) * a for a in (1, 1, 0.7, 0.6, 0.3, 0.4, 0.2)])
    hair = _palette("hair")[rng.choice(len(w), p=w / w.sum())] * rng.uniform(0.85, 1.15)
    colors = {k: _rgb(v) for k, v in colors.items()}
    return Outfit(_rgb(skin), top, bottoms, shoes, colors, patterns, _rgb(hair))


def _pulse(x: np.ndarray, duty: float, width: np.ndarray) -> np.ndarray:
    """Pulse train (1 on [k, k + duty)) box-filtered over [x - width / 2, x + width / 2]."""
    width = np.maximum(width, 1e-6)

    def integral(t):
        return np.floor(t) * duty + np.minimum(t - np.floor(t), duty)

    return (integral(x + width / 2) - integral(x - width / 2)) / width


def _check(name: str, a: np.ndarray, shape: tuple, kind: str = "iuf") -> np.ndarray:
    a = np.asarray(a)
    ok = a.ndim == len(shape) and all(s is None or s == t for s, t in zip(shape, a.shape, strict=True))
    if not ok or a.dtype.kind not in kind or a.size == 0 or (kind != "iu" and not np.isfinite(a).all()):
        raise ValueError(f"{name} must be a non-empty finite array of shape {shape}, got {a.shape} {a.dtype}")
    return a.astype(np.int64 if kind == "iu" else np.float64)


def make_albedo(
    uv: np.ndarray,
    faces_uv: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    vertex_bones: np.ndarray,
    bone_names: list[str],
    joints: np.ndarray,
    outfit: Outfit,
    rng: np.random.Generator,
    size: int = 1024,
    cuts_out: dict[str, float] | None = None,
    detail: SkinDetail | None = None,
) -> np.ndarray:
    """Paint an outfit into an albedo texture (see the module docstring for the method).

    Args:
        uv: (U, 2) texture coordinates in [0, 1], v up (v = 0 is the bottom row of the image).
        faces_uv: (F, 3) int indices into ``uv``.
        vertices: (V, 3) rest-pose positions in metres, Y up, body facing +Z.
        faces: (F, 3) int indices into ``vertices``, triangle by triangle with ``faces_uv``.
        vertex_bones: (V,) int index into ``bone_names`` of each vertex's dominant bone.
        bone_names: (J,) names including the BLSM bones of ``blsm.skeleton.BONE_NAMES`` (any order).
        joints: (J, 3) rest positions of the bone heads in metres, in ``bone_names`` order.
        outfit: what to paint (:func:`sample_outfit`).
        rng: random generator for hem heights, pattern scales and noise.
        size: texture width and height in texels (at least 8).
        cuts_out: a dict that receives the drawn borders (:func:`draw_cuts`), or None.
        detail: a :class:`synth.skin_detail.SkinDetail` to paint over the skin (face features, skin
            and hand detail; it does not draw from ``rng``), or None for none.

    Returns:
        (size, size, 3) uint8 sRGB albedo; row 0 is the top of the image (v = 1).

    Raises:
        ValueError: naming the argument, for wrong shapes or types, out-of-range indices, uv outside
            [0, 1] by more than 1e-3, missing bones or size < 8.
    """
    uv, faces_uv, vertices, faces, vertex_bones, joints = _checked_albedo_inputs(
        uv, faces_uv, vertices, faces, vertex_bones, bone_names, joints, size)
    body = _Texels.of(uv, faces_uv, vertices, faces, vertex_bones, bone_names, joints, int(size))
    cuts = draw_cuts(outfit, rng)
    if cuts_out is not None:
        cuts_out.update(cuts)
    label = _garment_labels(body, outfit, cuts)
    colour = _garment_colours(body, label, outfit, rng)
    if detail is not None:
        from synth.skin_detail import paint_detail

        colour = paint_detail(body, faces, label, colour, outfit, detail)
    # Step 1's fill: every texel outside the charts copies its nearest covered texel.
    img = np.zeros((size * size, 3))
    img[body.texels] = colour
    empty = np.ones(size * size, bool)
    empty[body.texels] = False
    iy, ix = ndimage.distance_transform_edt(
        empty.reshape(size, size), return_distances=False, return_indices=True
    )
    return np.round(linear_to_srgb(img.reshape(size, size, 3)[iy, ix]) * 255).astype(np.uint8)


def _checked_albedo_inputs(uv, faces_uv, vertices, faces, vertex_bones, bone_names, joints, size) -> tuple:
    """:func:`make_albedo`'s arrays as int64 and float64, or a ValueError naming the bad one."""
    if not isinstance(size, int | np.integer) or size < 8:
        raise ValueError(f"size must be an integer >= 8, got {size!r}")
    uv, vertices = _check("uv", uv, (None, 2), "iuf"), _check("vertices", vertices, (None, 3))
    faces_uv, faces = _check("faces_uv", faces_uv, (None, 3), "iu"), _check("faces", faces, (None, 3), "iu")
    vertex_bones = _check("vertex_bones", vertex_bones, (len(vertices),), "iu")
    joints = _check("joints", joints, (len(bone_names), 3))
    if uv.min() < -1e-3 or uv.max() > 1 + 1e-3:
        raise ValueError(f"uv must lie in [0, 1], got values in [{uv.min():.4g}, {uv.max():.4g}]")
    if faces_uv.min() < 0 or faces_uv.max() >= len(uv):
        raise ValueError(f"faces_uv indices must lie in [0, {len(uv)})")
    if faces.shape != faces_uv.shape or faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(
            f"faces must have the shape of faces_uv {faces_uv.shape}, indices in [0, {len(vertices)})"
        )
    if vertex_bones.min() < 0 or vertex_bones.max() >= len(bone_names):
        raise ValueError(f"vertex_bones must index bone_names, in [0, {len(bone_names)})")
    if missing := sorted({b for bones in PARTS for b in bones} - set(bone_names)):
        raise ValueError(f"bone_names lacks {missing}")
    return uv, faces_uv, vertices, faces, vertex_bones, joints


@dataclass(frozen=True)
class _Texels:
    """Step 1 of the module docstring: the covered texels of a body's texture, each with its 3D rest
    position and body part.

    Attributes:
        texels: (N,) flat texel indices; ``face`` (N,) and ``bary`` (N, 3) the UV triangle there.
        corners: (N, 3) the face's vertices.
        p: (N, 3) rest position, metres.
        texel_m: (N,) a texel's size on the body, metres.
        vn: (V, 3) area-weighted vertex normals (not unit).
        part: (N,) index into ``PARTS``.
        vertices, vertex_bones, bone_names: the body's.
        j: bone name -> (3,) rest position of its head.
    """

    texels: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    corners: np.ndarray
    p: np.ndarray
    texel_m: np.ndarray
    vn: np.ndarray
    part: np.ndarray
    vertices: np.ndarray
    vertex_bones: np.ndarray
    bone_names: list[str]
    j: dict[str, np.ndarray]

    @staticmethod
    def of(uv, faces_uv, vertices, faces, vertex_bones, bone_names, joints, size: int) -> _Texels:
        j = {name: joints[i] for i, name in enumerate(bone_names)}
        uv = np.clip(uv, 0, 1)
        texels, face, bary = rasterise_uv(uv, faces_uv, size)
        tri = uv_triangles(uv, faces_uv, size)
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        det = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])  # each face's doubled UV area, texels
        corners = faces[face]  # (N, 3)
        p = sum(bary[:, k, None] * vertices[corners[:, k]] for k in range(3))
        fn = np.cross(*(vertices[faces[:, 1:]] - vertices[faces[:, :1]]).transpose(1, 0, 2))  # 2 x area
        texel_m = np.sqrt(np.linalg.norm(fn, axis=1) / np.maximum(det, 1e-12))[face]  # texel size (m)
        vn = np.stack([np.bincount(faces.ravel(), np.repeat(fn[:, c], 3), len(vertices)) for c in range(3)], 1)
        part_of_bone = np.full(len(bone_names), -1)
        for q, bones in enumerate(PARTS):
            part_of_bone[[bone_names.index(b) for b in bones]] = q
        cp = part_of_bone[vertex_bones][corners]  # the part with the largest interpolated one-hot weight
        same = np.stack([sum(bary[:, k] * (cp[:, k] == cp[:, c]) for k in range(3)) for c in range(3)], 1)
        part = np.take_along_axis(cp, same.argmax(1)[:, None], 1)[:, 0]
        return _Texels(texels, face, bary, corners, p, texel_m, vn, part, vertices, vertex_bones, bone_names, j)

    @staticmethod
    def at_vertices(vertices, vertex_bones, bone_names, joints) -> _Texels:
        """The mesh's vertices as points of step 2 (each vertex's part is its bone's)."""
        part_of_bone = np.full(len(bone_names), -1)
        for q, bones in enumerate(PARTS):
            part_of_bone[[bone_names.index(b) for b in bones]] = q
        n, e = len(vertices), np.zeros(0)
        j = {name: joints[i] for i, name in enumerate(bone_names)}
        return _Texels(np.arange(n), e, e, e, vertices, e, e, part_of_bone[vertex_bones], vertices, vertex_bones,
                       bone_names, j)  # fmt: skip

    def along(self, a: str, b: str, m: np.ndarray) -> np.ndarray:
        """Fraction along joint ``a`` -> ``b`` (``_l`` or ``_r`` by side) of the limb texels ``m``."""
        left = (self.part == 3) | (self.part == 5)
        out = np.full(len(self.p), np.inf)
        for side, sm in (("_l", m & left), ("_r", m & ~left)):
            d = self.j[b + side] - self.j[a + side]
            out[sm] = (self.p[sm] - self.j[a + side]) @ d / (d @ d)
        return out

    def centre(self, bone: str, mask: np.ndarray | bool = True) -> np.ndarray:
        """The mean rest position of ``bone``'s vertices (``mask``: of those only)."""
        return self.vertices[(self.vertex_bones == self.bone_names.index(bone)) & mask].mean(0)

    @property
    def unit(self) -> float:
        """About 1 for an adult: the body's head-to-ankle height over 1.4 m."""
        return (self.j["head"][1] - self.j["ankle_l"][1]) / 1.4


def draw_cuts(outfit: Outfit, rng: np.random.Generator) -> dict[str, float]:
    """The random borders of step 2 (hem heights, waist, neckline, sleeve lengths, armholes,
    hairline) as fractions of body measures, drawn in :func:`make_albedo`'s order. Stored with the
    subject (``meta["outfit_cuts"]``) so that :mod:`synth.garments` cuts its cloth where the paint
    changes colour (:func:`vertex_labels`)."""
    c: dict[str, float] = {}
    if outfit.shoes == "shoes":
        c["shoe_line"], c["shoe_toe"] = rng.uniform(-0.005, 0.045), rng.uniform(-0.12, 0.03)
        c["sole"] = rng.uniform(0.008, 0.025)
    c["waist"] = rng.uniform(0.5, 1.8)
    lo, hi = HEMS[outfit.bottoms][2:]
    c["leg_hem"] = rng.uniform(lo, hi)
    lo, hi = (-1.0, -0.3) if outfit.top == "tank" else (-0.3, 0.2)
    c["neck_front"], c["neck_back"] = rng.uniform(lo, hi), rng.uniform(0.4, 0.8)
    c["top_hem"] = rng.uniform(0.0, 1.5)
    if outfit.top == "tshirt":
        c["sleeve"] = rng.uniform(0.3, 0.6)
    elif outfit.top == "longsleeve":
        c["sleeve"] = rng.uniform(0.9, 1.0)
    else:
        c["armhole_x"], c["armhole_y"] = rng.uniform(0.35, 0.55), rng.uniform(1.0, 1.4)
    c["hairline"] = rng.uniform(-0.35, 0.1)
    return {k: float(v) for k, v in c.items()}


def _garment_labels(body: _Texels, outfit: Outfit, c: dict[str, float]) -> np.ndarray:
    """Step 2 of the module docstring: per point 0 skin, 1 top, 2 bottoms, 3 shoes, 4 soles, 5 hair,
    for the borders ``c`` (:func:`draw_cuts`)."""
    j, vertices, unit = body.j, body.vertices, body.unit
    x, y, z = body.p.T
    head, neck, torso = body.part == 0, body.part == 1, body.part == 2
    arm, leg, left = (body.part == 3) | (body.part == 4), body.part >= 5, (body.part == 3) | (body.part == 5)
    y_pel, y_s1, y_c, y_n = (j[b][1] for b in ("pelvis", "spine_01", "clavicle_l", "neck"))
    label = np.zeros(len(body.p), np.int64)
    if outfit.shoes == "shoes":  # the foot below a line near the ankle joint (lower at the toes)
        ank = np.where(left[:, None], j["ankle_l"], j["ankle_r"])
        line = ank[:, 1] + unit * c["shoe_line"] + c["shoe_toe"] * np.maximum(z - ank[:, 2], 0)
        label[leg & (y < line)] = 3
        label[leg & (y < vertices[:, 1].min() + unit * c["sole"])] = 4
    # Bottoms: torso and legs below the waist, down to a hem perpendicular to the thigh or shin.
    waist = y_pel + c["waist"] * (y_s1 - y_pel)
    a, b = HEMS[outfit.bottoms][:2]
    label[(y < waist) & (torso | (leg & (body.along(a, b, leg) < c["leg_hem"])))] = 2
    # Top: torso (and hips) between the hem and the neckline; sleeves by type.
    nc = body.centre("neck")
    rn = np.hypot(x - nc[0], z - nc[2])
    y_front, y_back = y_c + c["neck_front"] * (y_n - y_c), y_c + c["neck_back"] * (y_n - y_c)
    front = 0.5 + 0.5 * (z - nc[2]) / np.maximum(rn, 1e-9)  # 1 at the front of the neck, 0 at the back
    neckline = y_back + (y_front - y_back) * front**1.5 + 1.5 * np.maximum(rn - 0.07 * unit, 0)
    hem = waist - c["top_hem"] * (y_s1 - y_pel)
    top = (torso | neck | leg) & (y < np.minimum(neckline, y_n)) & (y > hem)
    if outfit.top == "tshirt":
        top |= arm & (body.along("shoulder", "elbow", arm) < c["sleeve"])
    elif outfit.top == "longsleeve":
        top |= arm & (body.along("elbow", "wrist", arm) < c["sleeve"])
    else:  # armholes: straps above the shoulder joint, an elliptic cut-out below it
        xs, ys = j["shoulder_l"][0] - j["pelvis"][0], j["shoulder_l"][1]
        ax, ay = c["armhole_x"] * xs, c["armhole_y"] * (ys - j["spine_03"][1])
        ex = np.abs(x - j["pelvis"][0])
        top &= ~(((y >= ys) & (ex > xs - ax)) | (((ex - xs) / ax) ** 2 + ((y - ys) / ay) ** 2 < 1))
    label[top] = 1
    # Hair: a cap above a hairline high at the front, at the ears on the sides, low at the back.
    skull = body.centre("head", vertices[:, 1] > j["head"][1])
    h_head = vertices[body.vertex_bones == body.bone_names.index("head"), 1].max() - j["head"][1]
    fh = (z - skull[2]) / np.maximum(np.hypot(x - skull[0], z - skull[2]), 1e-9)  # +1 front, -1 back
    back = c["hairline"]
    hairline = j["head"][1] + h_head * (0.45 + (0.72 - back) / 2 * fh + (back - 0.18) / 2 * fh**2)
    label[(head | neck) & (y > hairline)] = 5
    return label


def vertex_labels(
    vertices: np.ndarray, vertex_bones: np.ndarray, bone_names: list[str], joints: np.ndarray, outfit: Outfit,
    cuts: dict[str, float],
) -> np.ndarray:
    """Step 2 at the mesh's vertices instead of its texels: (V,) labels as :func:`make_albedo`
    painted them (0 skin, 1 top, 2 bottoms, 3 shoes, 4 soles, 5 hair), given the same ``vertices``
    (the scan's pose), bones, joints, outfit and the stored ``cuts``. A vertex's part is its own
    bone's (a texel's is the largest interpolated one), so labels can differ from the paint only at
    part borders."""
    vertices = np.asarray(vertices, np.float64)
    vertex_bones = np.asarray(vertex_bones, np.int64)
    pts = _Texels.at_vertices(vertices, vertex_bones, list(bone_names), np.asarray(joints, np.float64))
    return _garment_labels(pts, outfit, cuts)


def _garment_colours(body: _Texels, label: np.ndarray, outfit: Outfit, rng: np.random.Generator) -> np.ndarray:
    """Step 3 of the module docstring: (N, 3) linear RGB of the labelled texels, patterns included."""
    p, bary, corners = body.p, body.bary, body.corners
    table = rng.uniform(size=4096)
    colour = np.empty((len(p), 3))
    m = label == 0
    low = 0.5 * value_noise(p[m] / 0.12, table) + 0.5 * value_noise(p[m] / 0.05 + 7.3, table)
    colour[m] = np.asarray(outfit.skin) * (1 + 0.06 * (low - 0.5))[:, None]
    for lab, name in ((1, "top"), (2, "bottoms"), (3, "shoes"), (5, "hair")):
        if not (m := label == lab).any():
            continue
        pat = outfit.patterns.get(name, "plain")
        base = np.asarray(outfit.hair if name == "hair" else outfit.colors[name])
        alt = np.asarray(outfit.colors.get(name + "_alt", base))
        period = rng.uniform(0.015, 0.06) * body.unit
        q, w = p[m] + rng.uniform(0, period, 3), body.texel_m[m] / period
        grain = value_noise(q / 0.004 * np.array([1, 0.3, 1]), table) + value_noise(q / 0.02, table[::-1].copy())
        mix = np.zeros(len(q))
        if pat == "stripes":
            mix = _pulse(q[:, 1] / period, rng.uniform(0.2, 0.5), w)
        elif pat in ("checks", "dots"):  # coordinates on the plane facing the normal's dominant axis
            n = np.abs(sum(bary[m, k, None] * body.vn[corners[m, k]] for k in range(3))).argmax(1)
            u, v = np.where(n == 0, q[:, 2], q[:, 0]) / period, np.where(n == 1, q[:, 2], q[:, 1]) / period
            if pat == "checks":
                mix = 0.5 * (_pulse(u, 0.5, w) + _pulse(v, 0.5, w))
            else:
                row = np.floor(v)
                d = np.hypot((u + 0.5 * row) % 1 - 0.5, v - row - 0.5)
                mix = np.clip((rng.uniform(0.15, 0.3) - d) / np.maximum(w, 1e-3) + 0.5, 0, 1)
        amp = 0.25 if name == "hair" else 0.16 if pat == "heather" else 0.04
        colour[m] = (base + mix[:, None] * (alt - base)) * (1 + amp * (grain - 1))[:, None]
    colour[label == 4] = outfit.colors["soles"]
    return colour
