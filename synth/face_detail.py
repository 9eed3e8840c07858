"""The face painted over a procedural albedo by :func:`synth.skin_detail.paint_detail`: its frame
and relief, eyeballs in the empty eye sockets, eyes, eyebrows, lips, flush and facial hair.

**The face frame.** Origin between the two eye keypoints (BLSM's ``left_eye`` and ``right_eye`` on
the subject's registration), x towards the person's left eye, y up, z forward, in units of ``e``,
half the distance between the eyes (about 31 mm for an adult; children scale with it). The head and
neck are rasterised orthographically along z into a *relief* (the nearest surface seen from the
front, ``RELIEF_RES`` pixels per ``e``): a texel is *seen from the front* when it lies on it.

**Eyeballs.** Anny's mesh without eyes has an empty socket, 25 mm deep, behind each eye opening: a
painted eye there would stay black. :func:`fit_eyeballs` finds each opening (where the relief falls
deep into the head near the keypoint) and moves the socket's vertices forward onto a sphere of 12 mm
radius just behind the lids. Only these vertices move (a few hundred, inside the head's outline).

- **eyes**: on the eyeball, sclera (pinker at the inner corner), an iris (radius 0.19 e, colour by
  skin tone, fibres and a darker rim) and a pupil; a dark lash line along the lid edges (thicker
  above) and a faint shadow under the eye;
- **eyebrows**: an arched band above each opening, thicker at the inner end, in the hair's colour
  (darker for light hair), streaked along the hairs' direction;
- **lips**: the mouth is the deepest crease of the relief's mid-line below the nose tip (its highest
  point); the upper lip (with a cupid's bow) and the fuller lower lip are redder and darker than the
  skin, with a dark line between them;
- **flush**: redness at the nose tip and wings, on the cheeks and on the ears;
- **facial hair** (some adult men, by the phenotype's ``gender`` and ``age_years``): stubble (fine
  dark dots), a full beard or a goatee, below a line from the mouth corner to the sideburns (by the
  angle around the axis through the ears) and above the upper neck, the lips left bare.

The painting functions take the person's choices as ``detail``, a
:class:`synth.skin_detail.SkinDetail` (this module does not import it: the dependency goes one way).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from synth.raster import rasterise

FACE_POINTS = ("nose", "left_eye", "right_eye", "left_ear", "right_ear")
LUM = np.array([0.2126, 0.7152, 0.0722])  # luminance of linear RGB
_SCLERA = np.array([0.72, 0.66, 0.6])  # linear RGB
_IRIS, _PUPIL = 0.19, 0.07  # radii, units of e (about 6 and 2 mm)
RELIEF_RES = 60  # relief pixels per e


def smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    """0 below ``edge0``, 1 above ``edge1`` (or the reverse where ``edge1`` < ``edge0``), smooth between."""
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def mix(colour: np.ndarray, m: np.ndarray, target: np.ndarray, alpha: np.ndarray) -> None:
    """In place: ``colour[m]`` towards ``target`` ((3,) or (n, 3)) by ``alpha`` (n,)."""
    a = np.clip(alpha, 0.0, 1.0)[:, None]
    colour[m] = colour[m] * (1 - a) + np.asarray(target) * a


def scale(colour: np.ndarray, m: np.ndarray, factor: np.ndarray, alpha: np.ndarray) -> None:
    """In place: multiply ``colour[m]`` by ``factor`` (3,) to the extent ``alpha`` (n,)."""
    a = np.clip(alpha, 0.0, 1.0)[:, None]
    colour[m] = colour[m] * (1 + a * (np.asarray(factor) - 1))


@dataclass(frozen=True)
class Face:
    """The face frame of the module docstring.

    Attributes:
        c: (3,) origin (metres); rot: (3, 3) rows x, y, z; e: half the distance between the eyes (m).
        relief: (H, W) nearest z (units of e) seen from the front, NaN where nothing; its pixel
            (0, 0) is at (u, w) = (``U0``, ``W1``), ``RELIEF_RES`` pixels per e, w down the rows.
        seen_z: (H, W) the relief's 3 x 3 minimum (a texel lookup's tolerance on slopes).
    """

    c: np.ndarray
    rot: np.ndarray
    e: float
    relief: np.ndarray
    seen_z: np.ndarray
    U0 = -3.5
    W1 = 3.0

    @staticmethod
    def of(points: dict[str, Any], vertices: np.ndarray, faces: np.ndarray, head_vertex: np.ndarray) -> Face:
        f = {k: np.asarray(v, np.float64) for k, v in points.items()}
        le, re = f["left_eye"], f["right_eye"]
        c, e = (le + re) / 2, float(np.linalg.norm(le - re) / 2)
        if e < 1e-4:
            raise ValueError("detail face: the eye keypoints coincide")
        x = (le - re) / (2 * e)
        y = np.array([0.0, 1.0, 0.0]) - x[1] * x
        y /= np.linalg.norm(y)
        rot = np.stack([x, y, np.cross(x, y)])
        if (f["nose"] - c) @ rot[2] <= 0:
            raise ValueError(
                "detail face: the nose must lie in front of the eyes (left_eye is the person's left)"
            )
        q = (vertices - c) @ rot.T / e
        fh = faces[head_vertex[faces].all(1)]
        fh = fh[np.argsort(q[fh].mean(1)[:, 2])]  # the nearest face drawn last wins
        w, h = int(7.0 * RELIEF_RES), int(8.5 * RELIEF_RES)
        tri = np.stack([(q[fh, 0] - Face.U0) * RELIEF_RES, (Face.W1 - q[fh, 1]) * RELIEF_RES], -1)
        pix, face, bary = rasterise(tri, w, h)
        relief = np.full(w * h, np.nan)
        relief[pix] = (bary * q[fh[face], 2]).sum(1)
        relief = relief.reshape(h, w)
        seen_z = ndimage.minimum_filter(np.nan_to_num(relief, nan=np.inf), 3)
        return Face(c, rot, e, relief, seen_z)

    def coords(self, p: np.ndarray) -> np.ndarray:
        """(N, 3) face coordinates (units of e) of points ``p`` (N, 3) in metres."""
        return (p - self.c) @ self.rot.T / self.e

    def pixel(self, uw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row and column of the relief pixel of face coordinates ``uw`` (N, 2), clipped."""
        h, w = self.relief.shape
        col = np.clip(np.round((uw[:, 0] - self.U0) * RELIEF_RES).astype(np.int64), 0, w - 1)
        row = np.clip(np.round((self.W1 - uw[:, 1]) * RELIEF_RES).astype(np.int64), 0, h - 1)
        return row, col

    def seen(self, q: np.ndarray, tol: float = 0.04) -> np.ndarray:
        """(N,) the points q (face coordinates) lie on the surface seen from the front."""
        row, col = self.pixel(q)
        return q[:, 2] >= self.seen_z[row, col] - tol

    def uw(self, row: np.ndarray, col: np.ndarray) -> np.ndarray:
        """Face coordinates (u, w) of relief pixels."""
        return np.stack([self.U0 + col / RELIEF_RES, self.W1 - row / RELIEF_RES], -1)


@dataclass(frozen=True)
class _Eye:
    """One eye opening: centre (u, w), half-width a and half-height b (units of e), its mask on the
    relief (H, W), and the eyeball behind it: centre (3,) in face coordinates and radius (units of e),
    or None where there is none (the eye is then painted on the surface)."""

    u: float
    w: float
    a: float
    b: float
    mask: np.ndarray
    ball: np.ndarray | None = None
    radius: float = 0.0


def _relief_uw(face: Face) -> np.ndarray:
    """(H, W, 2) face coordinates (u, w) of the relief's pixels."""
    h, w = face.relief.shape
    row, col = np.mgrid[0:h, 0:w]
    return face.uw(row.ravel(), col.ravel()).reshape(h, w, 2)


def _region(uw: np.ndarray, m: np.ndarray, ball: np.ndarray | None = None, radius: float = 0.0) -> _Eye:
    pts = uw[m]
    (cu, cw), (a, b) = pts.mean(0), 2 * pts.std(0)
    return _Eye(float(cu), float(cw), float(max(a, 0.2)), float(max(b, 0.06)), m, ball, radius)


def _pocket(face: Face, side: float) -> _Eye | None:
    """The opening of the eye at u = ``side`` (+1 left, -1 right) where the mesh has no eyeball:
    the largest region of the relief near the keypoint that falls deep into the head."""
    uw = _relief_uw(face)
    box = (np.abs(uw[..., 0] - side) < 0.8) & (np.abs(uw[..., 1]) < 0.6)  # the temples lie farther out
    deep = box & (np.nan_to_num(face.relief, nan=0.0) < -0.5)
    lab, n = ndimage.label(deep)
    if not n:
        return None
    sizes = ndimage.sum(deep, lab, range(1, n + 1))
    k = int(sizes.argmax()) + 1
    return _region(uw, lab == k) if sizes[k - 1] >= 0.05 * RELIEF_RES**2 else None


def _eyes(face: Face, eyes: dict[str, Any]) -> list[_Eye]:
    """Both eyes: where an eyeball is given (:func:`fit_eyeballs`), the opening is where the relief
    shows it; else an almond of usual size at the keypoint, painted on the surface."""
    uw = _relief_uw(face)
    out = []
    for name, side in (("left_eye", 1.0), ("right_eye", -1.0)):
        if name in eyes:
            ball = face.coords(np.asarray(eyes[name][:3], np.float64)[None])[0]
            radius = float(eyes[name][3]) / face.e
            d = np.sqrt(
                (uw[..., 0] - ball[0]) ** 2 + (uw[..., 1] - ball[1]) ** 2 + (face.relief - ball[2]) ** 2
            )
            m = np.nan_to_num(d, nan=np.inf) < radius + 0.03
            if m.sum() >= 0.02 * RELIEF_RES**2:
                out.append(_region(uw, m, ball, radius))
                continue
        a, b = 0.42, 0.13
        out.append(_Eye(side, 0.0, a, b, ((uw[..., 0] - side) / a) ** 2 + (uw[..., 1] / b) ** 2 < 1))
    return out


def fit_eyeballs(
    vertices: np.ndarray, faces: np.ndarray, head_vertex: np.ndarray, points: dict[str, Any]
) -> tuple[np.ndarray, dict[str, tuple[float, float, float, float]]]:
    """Close the empty eye sockets of a mesh without eyeballs (Anny's ``noeyes`` topology) with
    eyeballs, so that painted eyes are lit: the vertices of each socket (behind the lids, inside
    the opening or hidden from the front) move forward onto a sphere of radius 0.4 e (about 12 mm)
    whose front lies just behind the lids, or onto its centre plane outside its disc.

    Args:
        vertices: (V, 3) rest positions, metres (Y up, facing +Z).
        faces: (F, 3) triangles.
        head_vertex: (V,) bool, the vertices of the head and neck.
        points: ``FACE_POINTS`` -> (3,) rest keypoints, metres.

    Returns:
        The new (V, 3) vertices (a copy; only socket vertices move, and never backwards) and per eye
        found (``left_eye``, ``right_eye``) the eyeball's centre (metres) and radius (metres).
    """
    vertices = np.asarray(vertices, np.float64)
    face = Face.of(points, vertices, faces, head_vertex)
    q = face.coords(vertices)
    out, eyes = vertices.copy(), {}
    seen = face.seen(q)
    row, col = face.pixel(q[:, :2])
    for name, side in (("left_eye", 1.0), ("right_eye", -1.0)):
        eye = _pocket(face, side)
        if eye is None:
            continue
        ring = ndimage.binary_dilation(eye.mask, iterations=8) & ~ndimage.binary_dilation(
            eye.mask, iterations=2
        )
        lids = face.relief[ring]
        if not np.isfinite(lids).any():
            continue
        lid = float(np.median(lids[np.isfinite(lids)]))
        radius = 0.4
        zc = lid - 0.08 - radius
        du, dw = q[:, 0] - eye.u, q[:, 1] - eye.w
        deep = (q[:, 2] < lid - 0.25) & (q[:, 2] > zc - radius - 0.5)  # not the back of the head
        socket = head_vertex & (np.abs(du) < eye.a + 0.2) & (np.abs(dw) < eye.b + 0.5) & deep
        socket &= ~seen | eye.mask[row, col]
        sphere = zc + np.sqrt(np.clip(radius**2 - du**2 - dw**2, 0, None))
        z = np.maximum(q[:, 2], sphere)
        qn = np.stack([q[:, 0], q[:, 1], z], 1)[socket]
        out[socket] = face.c + face.e * qn @ face.rot
        centre = face.c + face.e * np.array([eye.u, eye.w, zc]) @ face.rot
        eyes[name] = (*(float(x) for x in centre), float(radius * face.e))
    return out, eyes


def _mouth_and_nose(face: Face) -> tuple[float, float]:
    """w of the nose tip (the relief's highest mid-line point between the eyes and the mouth) and
    of the mouth (its deepest crease between the nose tip and the chin), units of e."""
    mid = -int(round(face.U0 * RELIEF_RES))
    strip = face.relief[:, mid - 2 : mid + 3]
    n = np.isfinite(strip).sum(1)
    col = np.where(n > 0, np.nan_to_num(strip).sum(1) / np.maximum(n, 1), np.nan)
    ws = face.W1 - np.arange(len(col)) / RELIEF_RES
    ok = np.isfinite(col)
    nose = (ws < -0.8) & (ws > -2.2) & ok
    w_tip = float(ws[nose][np.argmax(col[nose])]) if nose.any() else -1.45
    k = int(0.25 * RELIEF_RES)
    crease = np.full(len(col), np.inf)
    crease[k:-k] = col[k:-k] - 0.5 * (col[: -2 * k] + col[2 * k :])
    search = (ws < w_tip - 0.7) & (ws > w_tip - 1.45) & np.isfinite(crease)
    w_mouth = float(ws[search][np.argmin(crease[search])]) if search.any() else w_tip - 1.0
    return w_tip, w_mouth


@dataclass(frozen=True)
class _Head:
    """The head and neck skin texels in the face frame: ``q`` (n, 3) face coordinates, ``seen``
    (n,) on the surface seen from the front, ``row``/``col`` their relief pixel, ``is_head`` (n,),
    ``texel`` (n,) a texel's size (units of e), ``points`` (5, 3) the ``FACE_POINTS``, and the w of
    the nose tip and the mouth."""

    q: np.ndarray
    seen: np.ndarray
    row: np.ndarray
    col: np.ndarray
    is_head: np.ndarray
    texel: np.ndarray
    points: np.ndarray
    w_tip: float
    w_mouth: float


def face_features(
    body: Any, face: Face, hm: np.ndarray, col: np.ndarray, detail: Any, skin_rgb: np.ndarray,
    hair_rgb: np.ndarray, table: np.ndarray, noise: Any,
) -> None:  # fmt: skip
    """Flush, eyes, eyebrows, lips and facial hair on the head and neck skin texels ``hm``, whose
    colours are ``col`` (n, 3, painted in place), in that order (features over the flush); ``body``
    as for :func:`synth.skin_detail.paint_detail`, ``detail`` its :class:`synth.skin_detail.SkinDetail`."""
    q = face.coords(body.p[hm])
    row, c = face.pixel(q[:, :2])
    points = face.coords(np.stack([np.asarray(detail.face[k]) for k in FACE_POINTS]))
    h = _Head(
        q, face.seen(q), row, c, body.part[hm] == 0, body.texel_m[hm] / face.e, points, *_mouth_and_nose(face)
    )
    _flush(h, col, detail)
    eyes = _eyes(face, detail.eyes)
    dist = ndimage.distance_transform_edt(~(eyes[0].mask | eyes[1].mask)) / RELIEF_RES  # from the openings
    for eye in eyes:
        _eye(h, col, eye, dist[row, c], detail, skin_rgb, hair_rgb, table, noise)
        _eyebrow(h, col, eye, detail, hair_rgb, table, noise)
    a_lip = _lips(h, col, detail)
    if detail.beard != "none":
        neck, head = face.coords(np.stack([body.j["neck"], body.j["head"]]))
        _facial_hair(h, col, body.p[hm], a_lip, neck, head, detail, hair_rgb, table, noise)


def _flush(h: _Head, col: np.ndarray, detail: Any) -> None:
    """Redness at the nose tip and wings, on the cheeks and on the ears."""
    u, w, z = h.q.T
    f = np.exp(-((u / 0.25) ** 2 + ((w - h.w_tip) / 0.25) ** 2))
    f += 0.7 * np.exp(-(((np.abs(u) - 0.35) / 0.15) ** 2 + ((w - h.w_tip + 0.25) / 0.15) ** 2))
    f += 0.7 * np.exp(-(((np.abs(u) - 1.15) / 0.4) ** 2 + ((w - h.w_tip - 0.05) / 0.4) ** 2))
    f *= h.seen & h.is_head & (z > -1.5)
    d_ear = np.minimum(np.linalg.norm(h.q - h.points[3], axis=1), np.linalg.norm(h.q - h.points[4], axis=1))
    f += 0.8 * np.exp(-((d_ear / 0.6) ** 2)) * h.is_head
    scale(col, np.ones(len(col), bool), [1.03, 0.8, 0.84], detail.flush * f)


def _eye(
    h: _Head, col: np.ndarray, eye: _Eye, dist: np.ndarray, detail: Any, skin_rgb: np.ndarray,
    hair_rgb: np.ndarray, table: np.ndarray, noise: Any,
) -> None:  # fmt: skip
    """One eye: the shadow under it, the eyeball (sclera, iris, pupil) and the lash line; ``dist``
    (n,) is each texel's relief distance from the openings (units of e)."""
    u, w, z = h.q.T
    du, dw = u - eye.u, w - eye.w
    box = h.is_head & (np.abs(du) < eye.a + 0.12) & (np.abs(dw) < 0.75)
    if eye.ball is not None:
        ball = box & (np.linalg.norm(h.q - eye.ball, axis=1) < eye.radius + 0.04) & (z > eye.ball[2])
    else:
        ball = box & h.seen & eye.mask[h.row, h.col]
    lid = box & ~ball
    below = np.clip(-dw - eye.b, 0, None)
    shade = (
        smoothstep(0.0, 0.08, below) * smoothstep(0.45, 0.1, below) * smoothstep(1.0, 0.5, np.abs(du) / eye.a)
    )
    scale(col, lid & h.seen, [0.88, 0.84, 0.9], 0.8 * shade[lid & h.seen])
    corner = smoothstep(-0.45, -0.9, np.sign(-eye.u) * du / eye.a)[ball, None]  # 1 at the nose's side
    rgb = _SCLERA * (1 - corner) + corner * skin_rgb * np.array([1.15, 0.8, 0.8])
    ri = np.hypot(du - detail.gaze[0], dw - detail.gaze[1])[ball]
    fibres = noise(np.stack([ri * 40, np.arctan2(dw[ball], du[ball]) * 6, np.zeros(len(ri))], 1), table)
    shade = (0.8 + 0.4 * fibres) * (1 - 0.5 * smoothstep(0.75 * _IRIS, _IRIS, ri))  # a darker rim
    soft = np.maximum(h.texel[ball], 0.015)
    a = np.clip((_IRIS - ri) / soft + 0.5, 0, 1)[:, None]
    rgb = rgb * (1 - a) + np.asarray(detail.iris) * shade[:, None] * a
    a = np.clip((_PUPIL - ri) / soft + 0.5, 0, 1)[:, None]
    col[ball] = rgb * (1 - a) + 0.01 * a
    # The lash line along the lid edges, thicker above; the lids' rim into the socket is dark too.
    upper = dw > 0
    thick = np.where(upper, 0.06, 0.025) * smoothstep(1.25, 0.7, np.abs(du) / eye.a)
    lash = lid & (dist < thick + 0.03)
    a = np.clip((thick - dist) / np.maximum(h.texel, 0.01) + 0.5, 0, 1) * np.where(upper, 0.9, 0.55)
    mix(col, lash, np.minimum(hair_rgb * 0.4, 0.02) + 0.005, a[lash])


def _eyebrow(
    h: _Head, col: np.ndarray, eye: _Eye, detail: Any, hair_rgb: np.ndarray, table: np.ndarray,
    noise: Any,
) -> None:  # fmt: skip
    """An arched band above the opening, thicker at the inner end, its hairs streaked upwards at
    the inner end and outwards along the rest."""
    u, w, z = h.q.T
    s = np.sign(eye.u)
    u_in = eye.u - s * 0.95 * eye.a
    t = s * (u - u_in) / (2.3 * eye.a)  # 0 at the inner end, 1 at the tail
    tc = np.clip(t, 0, 1)
    centre = eye.w + 0.6 + 0.14 * np.sin(np.pi * tc * 0.85) - 0.1 * tc**2
    half = 0.5 * detail.brow_width * (1 - 0.6 * tc)
    band = (
        np.clip((half - np.abs(w - centre)) / 0.03 + 0.5, 0, 1)
        * smoothstep(-0.06, 0.06, t)
        * smoothstep(1.04, 0.85, t)
    )
    brow = h.is_head & h.seen & (band > 0) & (z > -1.2)
    if not brow.any():
        return
    ang = np.where(t < 0.25, 1.2, 0.35) * s
    along = np.cos(ang) * (u - u_in) * s + np.sin(ang) * (w - centre)
    streak = noise(np.stack([along * 6, (w - centre - along * 0.2) * 45, z * 6], 1)[brow], table)
    rgb = hair_rgb * (0.5 if hair_rgb @ LUM > 0.2 else 0.7) + 0.002  # light hair, darker brows
    mix(col, brow, rgb, band[brow] * detail.brow * (0.7 + 0.5 * streak))


def _lips(h: _Head, col: np.ndarray, detail: Any) -> np.ndarray:
    """The upper lip (with a cupid's bow) and the fuller lower lip, and a dark line between them;
    returns each texel's lip coverage (n,)."""
    u, w, z = h.q.T
    r = np.abs(u) / 0.8  # the mouth is 1.6 e wide
    shape = np.sqrt(np.clip(1 - r**2, 0, 1))
    bow = 0.05 * np.exp(-(((np.abs(u) - 0.22) / 0.12) ** 2)) - 0.06 * np.exp(-((u / 0.08) ** 2))
    up, low = (0.19 + bow) * shape, 0.28 * shape**1.2
    dw = w - h.w_mouth
    edge = np.maximum(h.texel, 0.03)
    a = np.where(dw > 0, np.clip((up - dw) / edge + 0.5, 0, 1), np.clip((low + dw) / edge + 0.5, 0, 1))
    a *= (h.is_head & (z > -0.5) & (r < 1)) * smoothstep(1.0, 0.85, r)
    scale(col, np.ones(len(col), bool), np.asarray(detail.lips), a)
    line = np.clip((0.02 - np.abs(dw)) / edge + 0.5, 0, 1) * smoothstep(1.0, 0.8, r) * h.is_head * (z > -0.5)
    scale(col, np.ones(len(col), bool), [0.55, 0.45, 0.45], line)
    return a


def _facial_hair(
    h: _Head, col: np.ndarray, p: np.ndarray, a_lip: np.ndarray, neck: np.ndarray, head: np.ndarray,
    detail: Any, hair_rgb: np.ndarray, table: np.ndarray, noise: Any,
) -> None:  # fmt: skip
    """Stubble, a beard or a goatee: below a line from the mouth corners to the sideburns, above
    the upper neck (a fifth of the way from the neck joint to the head joint, ``neck`` and ``head`` in face
    coordinates), the lips left bare; ``p`` (n, 3) are the texels' positions in metres."""
    u, w, z = h.q.T
    ear_z, ear_w = h.points[3:, 2].mean(), h.points[3:, 1].mean()
    # The angle around the head's vertical axis through the ears: 0 in front, 90 degrees at the ears.
    theta = np.degrees(np.arctan2(np.abs(u), z - ear_z))
    t_mouth = np.degrees(np.arctan2(0.8, max(-ear_z, 0.5)))  # at the mouth corners
    t = np.clip((theta - t_mouth) / (72.0 - t_mouth), 0, 1)
    top = np.where(theta < t_mouth, h.w_tip - 0.4, (h.w_mouth + 0.45) * (1 - t) + (ear_w - 0.3) * t)
    top = np.where(theta > 72.0, ear_w + 1.2, top)  # the sideburns, up to the hair
    if detail.beard == "goatee":
        top = np.where(theta < t_mouth, top, h.w_mouth - 0.5)
        sides = smoothstep(t_mouth + 8, t_mouth, theta)
    else:
        sides = smoothstep(88.0, 80.0, theta)
    front = (z - neck[2]) / np.maximum(np.hypot(u - neck[0], z - neck[2]), 1e-6)
    neck_front = np.where(h.is_head, 1.0, smoothstep(-0.3, 0.3, front))
    w_low = neck[1] + 0.2 * (head[1] - neck[1])  # under the chin
    ragged = noise(h.q * 4 + 5.5, table) - 0.5
    area = smoothstep(0.0, 0.12, top - w + 0.1 * ragged) * smoothstep(
        w_low - 0.3, w_low + 0.2, w + 0.3 * ragged
    )
    area *= sides * neck_front * (1 - a_lip)
    m = area > 0
    if detail.beard == "stubble":  # fine dark dots
        dots = smoothstep(0.45, 0.7, noise(p[m] / 0.0006, table))
        a = detail.beard_density * (0.25 + 0.3 * dots)
        rgb = hair_rgb * (0.45 if hair_rgb @ LUM > 0.2 else 0.7)
    else:
        streak = noise(p[m] / np.array([0.0015, 0.006, 0.0015]), table)  # hairs along y
        a = detail.beard_density * (0.8 + 0.25 * streak)
        rgb = hair_rgb[None] * (0.75 + 0.5 * streak[:, None])
    mix(col, m, rgb, a * area[m])
