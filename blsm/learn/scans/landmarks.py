"""The rules that place CAESAR-like anatomical landmarks on the BLSM template (thesis Eq. 5.13).

Eq. 5.13 fits the skeleton to a scan through landmarks: ``A_lm`` selects the template's landmark
points and compares them with the landmarks located on the scan. CAESAR scans come with about 70
hand-placed anatomical landmarks; this module defines the same kind of set on the packaged BLSM
template with geometric rules (the extreme vertex of a bone's region along a direction near a
joint, a point of the sagittal profile at a given height, ...). Rules are written for the body's
left side (+X) and mirrored with ``model.vertex_mirror``, so left/right pairs are exact mirrors;
midline landmarks are chosen among the template vertices on the plane x = 0.

The result is stored in ``blsm/data/landmarks.yaml`` (``python -m blsm.learn.scans.landmarks`` rewrites
it); :mod:`blsm.learn.scans.format` reads that file, and a test checks it equals :func:`compute_landmarks`
on the packaged model. Positions are the rest template's (metres, Y up, facing +Z, +X = left).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

LANDMARKS_YAML = Path(__file__).resolve().parents[2] / "data" / "landmarks.yaml"


@dataclass(frozen=True)
class Landmark:
    """One landmark of the table.

    Attributes:
        name: e.g. ``acromion_l``; left/right pairs end in ``_l`` / ``_r``, midline ones in neither.
        vertex: template vertex index.
        comment: the anatomical meaning and the rule, one line.
    """

    name: str
    vertex: int
    comment: str


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


class _Rules:
    """Geometric queries on the rest template (numpy, float64)."""

    def __init__(self, model) -> None:
        self.t = model.template.detach().cpu().numpy().astype(np.float64)  # (V, 3)
        self.heads = model.heads.detach().cpu().numpy().astype(np.float64)  # (J, 3)
        self.bones = model.vertex_bones.detach().cpu().numpy()
        self.mirror = model.vertex_mirror.detach().cpu().numpy()
        self.names = list(model.bone_names)
        self.mid = np.flatnonzero(self.t[:, 0] == 0.0)
        if len(self.mid) < 20:
            raise ValueError("template has no vertices on the plane x = 0; cannot place midline landmarks")
        self.left = np.flatnonzero(self.t[:, 0] > 0.0)

    def h(self, bone: str) -> np.ndarray:
        return self.heads[self.names.index(bone)]

    def region(self, *bones: str, left: bool = True) -> np.ndarray:
        ids = [self.names.index(b) for b in bones]
        idx = np.flatnonzero(np.isin(self.bones, ids))
        return idx[self.t[idx, 0] > 0.0] if left else idx

    def extreme(self, idx: np.ndarray, direction, what: str) -> int:
        if len(idx) == 0:
            raise RuntimeError(f"landmark rule for {what}: no candidate vertices")
        return int(idx[np.argmax(self.t[idx] @ np.asarray(direction, dtype=np.float64))])

    def band(self, idx: np.ndarray, axis: int, value: float, half: float) -> np.ndarray:
        return idx[np.abs(self.t[idx, axis] - value) <= half]

    def slab(self, idx: np.ndarray, origin: np.ndarray, normal: np.ndarray, half: float) -> np.ndarray:
        return idx[np.abs((self.t[idx] - origin) @ normal) <= half]

    def near(self, idx: np.ndarray, point: np.ndarray, radius: float) -> np.ndarray:
        return idx[np.linalg.norm(self.t[idx] - point, axis=1) <= radius]

    def closest(self, idx: np.ndarray, point: np.ndarray) -> int:
        return int(idx[np.argmin(np.linalg.norm(self.t[idx] - point, axis=1))])

    def profile(self, front: bool, y: float, half: float = 0.006) -> int:
        """Midline vertex at height ``y`` on the front (max z) or back (min z) profile.

        The midline vertices are sparse (a band of +-6 mm can hold only the front vertex), so the
        candidates are first split into front and back by the middle of the body's sagittal
        section at that height; then the outer vertex of the band on the asked side is taken, or
        the side's vertex nearest in height when the band holds none there.
        """
        wide = self.band(self.mid, 1, y, 0.03)
        if len(wide) < 2:
            raise RuntimeError(f"profile at height {y:.3f}: fewer than 2 midline vertices near it")
        z = self.t[wide, 2]
        centre = 0.5 * (z.max() + z.min())
        side = wide[z > centre] if front else wide[z < centre]
        c = self.band(side, 1, y, half)
        if len(c) == 0:
            return int(side[np.argmin(np.abs(self.t[side, 1] - y))])
        zc = self.t[c, 2]
        return int(c[np.argmax(zc)] if front else c[np.argmin(zc)])

    def lateral_dir(self, axis: np.ndarray) -> np.ndarray:
        """+X (the body's left, i.e. lateral on the left side) made orthogonal to ``axis``."""
        x = np.array([1.0, 0.0, 0.0])
        return _unit(x - (x @ axis) * axis)


UP = np.array([0.0, 1.0, 0.0])
FRONT = np.array([0.0, 0.0, 1.0])
X_POS = np.array([1.0, 0.0, 0.0])  # lateral on the body's left


class _Table:
    """The landmarks placed so far: midline ones, and left ones (mirrored to the right at the end)."""

    def __init__(self, rules: _Rules) -> None:
        self.t = rules.t
        self.mirror = rules.mirror
        self.mid: list[Landmark] = []
        self.left: list[Landmark] = []

    def add_mid(self, name: str, v: int, comment: str) -> None:
        if self.t[v, 0] != 0.0:
            raise RuntimeError(f"midline landmark {name} is off the plane x = 0")
        self.mid.append(Landmark(name, int(v), comment))

    def add_left(self, name: str, v: int, comment: str) -> None:
        if self.t[v, 0] <= 0.0:
            raise RuntimeError(f"left landmark {name}_l has x <= 0")
        self.left.append(Landmark(f"{name}_l", int(v), comment))

    def landmarks(self) -> list[Landmark]:
        """Midline landmarks, then left landmarks each followed by its mirrored right partner."""
        out = list(self.mid)
        for lm in self.left:
            out.append(lm)
            out.append(Landmark(lm.name[:-2] + "_r", int(self.mirror[lm.vertex]), "mirror of " + lm.name))
        names = [lm.name for lm in out]
        if len(set(names)) != len(names):
            raise RuntimeError("duplicate landmark names")
        return out


def compute_landmarks(model) -> list[Landmark]:
    """Place every landmark on ``model``'s rest template by its rule.

    Args:
        model: a :class:`blsm.BLSM` whose template is symmetric about x = 0 (``vertex_mirror``).

    Returns:
        Midline landmarks, then left landmarks each followed by its mirrored right partner.
    """
    r = _Rules(model)
    table = _Table(r)
    ment = _head_midline(r, table)
    supra, sub_y, navel = _trunk_midline(r, table)
    _head_left(model, r, table, ment)
    _trunk_left(r, table, supra, sub_y, navel)
    _arm_left(r, table)
    _leg_left(r, table)
    return table.landmarks()


def _head_midline(r: _Rules, table: _Table) -> int:
    """Head and face on the midline; returns the menton (chin) vertex."""
    t = r.t
    head, neck = r.h("head"), r.h("neck")
    head_mid = r.mid[t[r.mid, 1] > neck[1]]
    top = r.extreme(head_mid, UP, "head_top")
    table.add_mid("head_top", top, "vertex: highest point of the head (midline max y)")
    face = head_mid[t[head_mid, 2] > head[2]]
    pron = r.extreme(face, FRONT, "pronasale")
    table.add_mid("pronasale", pron, "nose tip: most anterior midline point of the face")
    # Eye height: the most anterior point of the brow lies above it; the nasal root is the deepest
    # point of the profile between the nose tip and the brow.
    brow_band = face[(t[face, 1] > t[pron, 1] + 0.02) & (t[face, 1] < t[pron, 1] + 0.07)]
    glab = r.extreme(brow_band, FRONT, "glabella")
    table.add_mid("glabella", glab, "most anterior midline point of the brow, above the nasal root")
    between = face[(t[face, 1] > t[pron, 1] + 0.005) & (t[face, 1] < t[glab, 1])]
    sell = r.extreme(between, -FRONT, "sellion")
    table.add_mid("sellion", sell, "nasal root: deepest midline point between nose tip and glabella")
    chin = face[(t[face, 1] < t[pron, 1] - 0.03) & (t[face, 2] > head[2] + 0.04)]
    ment = r.extreme(chin, -UP, "menton")
    table.add_mid("menton", ment, "chin: lowest midline point of the mandible's front")
    back_head = head_mid[(t[head_mid, 2] < head[2]) & (t[head_mid, 1] > head[1])]
    table.add_mid(
        "opisthocranion",
        r.extreme(back_head, -FRONT, "opisthocranion"),
        "back of the head: most posterior midline point of the skull",
    )
    return ment


def _trunk_midline(r: _Rules, table: _Table) -> tuple[int, float, int]:
    """Trunk on the midline; returns the suprasternale vertex, the substernale height (m) and the
    navel vertex, which place the left trunk landmarks."""
    t = r.t
    neck = r.h("neck")
    table.add_mid(
        "cervicale",
        r.profile(False, neck[1] - 0.01),
        "C7 spinous process: back midline at the base of the neck",
    )
    supra = r.profile(True, r.h("clavicle_l")[1] + 0.005)
    table.add_mid("suprasternale", supra, "jugular notch: front midline at the clavicles' medial ends")
    crotch = r.extreme(r.mid, -UP, "crotch")
    # The navel is the deepest dimple of the front midline profile between the hips and the ribs.
    belly = r.mid[
        (t[r.mid, 2] > r.h("pelvis")[2])
        & (t[r.mid, 1] > r.h("hip_l")[1] + 0.02)
        & (t[r.mid, 1] < r.h("spine_02")[1])
    ]
    depth = []
    for v in belly:
        nb = belly[np.abs(t[belly, 1] - t[v, 1]) < 0.03]
        depth.append(t[nb, 2].mean() - t[v, 2])
    navel = int(belly[int(np.argmax(depth))])
    sub_y = t[supra, 1] - 0.45 * (t[supra, 1] - t[navel, 1])
    table.add_mid(
        "substernale",
        r.profile(True, sub_y),
        "xiphoid: front midline about 45 % of the way from the jugular notch to the navel",
    )
    table.add_mid("omphalion", navel, "navel: deepest dimple of the front midline profile below the ribs")
    table.add_mid("crotch", crotch, "lowest midline point of the trunk, between the legs")
    table.add_mid(
        "back_t8",
        r.profile(False, r.h("spine_03")[1]),
        "T8 region: back midline at the height of the spine_03 joint",
    )
    table.add_mid("back_t10", r.profile(False, sub_y),
                  "T10 region: back midline at the height of substernale")
    table.add_mid("back_waist", r.profile(False, t[navel, 1]),
                  "back midline at the height of the navel (L3-L4)")
    return supra, sub_y, navel


def _head_left(model, r: _Rules, table: _Table, ment: int) -> None:
    """Ear, orbit and jaw on the left (from the model's eye and ear keypoints)."""
    t = r.t
    le = _keypoint(model, "left_eye")
    lear = _keypoint(model, "left_ear")
    head_l = r.region("head")
    table.add_left("tragion", r.closest(head_l, lear), "ear: template vertex nearest Anny's ear keypoint")
    below_eye = r.near(head_l, le - np.array([0.0, 0.02, 0.0]), 0.015)
    table.add_left(
        "infraorbitale",
        r.extreme(below_eye, FRONT, "infraorbitale"),
        "lowest point of the orbit's rim: most anterior point 2 cm below the eye keypoint",
    )
    jaw = head_l[
        (t[head_l, 1] < t[r.closest(head_l, lear), 1] - 0.03)
        & (t[head_l, 1] > t[ment, 1])
        & (t[head_l, 2] > lear[2] - 0.01)
    ]
    table.add_left(
        "gonion",
        r.extreme(jaw, _unit(np.array([1.0, -1.0, -0.5])), "gonion"),
        "jaw angle: lateral, low, posterior extreme of the face below the ear",
    )


def _trunk_left(r: _Rules, table: _Table, supra: int, sub_y: float, navel: int) -> None:
    """Chest, ribs, pelvis and hip on the left, at heights set by the midline landmarks."""
    t = r.t
    chest = r.region("spine_02", "spine_03")
    chest = chest[(t[chest, 0] > 0.04) & (t[chest, 1] < t[supra, 1] - 0.05) & (t[chest, 1] > sub_y - 0.03)]
    table.add_left("nipple", r.extreme(chest, FRONT, "nipple"), "most anterior point of the left chest")
    trunk = r.region("spine_01", "spine_02", "spine_03", "pelvis")
    rib_y = 0.5 * (sub_y + t[navel, 1])
    table.add_left(
        "rib10",
        r.extreme(r.band(trunk, 1, rib_y, 0.008), X_POS, "rib10"),
        "10th rib: lateral-most trunk point halfway between substernale and navel",
    )
    hip = r.h("hip_l")
    ilio_y = t[navel, 1]
    table.add_left(
        "iliocristale",
        r.extreme(r.band(trunk, 1, ilio_y, 0.008), X_POS, "iliocristale"),
        "top of the iliac crest: lateral-most trunk point at navel height",
    )
    pelvis_reg = r.region("pelvis", "spine_01", "hip_l")
    asis_y = hip[1] + 0.6 * (t[navel, 1] - hip[1])
    cand = r.band(r.band(pelvis_reg, 1, asis_y, 0.01), 0, 0.9 * hip[0], 0.012)
    table.add_left(
        "asis",
        r.extreme(cand, FRONT, "asis"),
        "anterior superior iliac spine: front at hip-joint x, 60 % from hip to navel height",
    )
    cand = r.band(r.band(pelvis_reg, 1, asis_y, 0.01), 0, 0.045, 0.01)
    table.add_left(
        "psis",
        r.extreme(cand, -FRONT, "psis"),
        "posterior superior iliac spine: back, 4.5 cm from the midline, at ASIS height",
    )
    thigh = r.region("pelvis", "hip_l")
    cand = thigh[(t[thigh, 1] < hip[1] + 0.01) & (t[thigh, 1] > hip[1] - 0.08)]
    table.add_left(
        "trochanterion",
        r.extreme(cand, X_POS, "trochanterion"),
        "greater trochanter: lateral-most point up to 8 cm below the hip joint",
    )


def _arm_left(r: _Rules, table: _Table) -> None:
    """Shoulder, elbow, wrist and hand on the left."""
    t = r.t
    sh, el, wr = r.h("shoulder_l"), r.h("elbow_l"), r.h("wrist_l")
    arm = r.region("clavicle_l", "shoulder_l", "spine_03")
    cand = arm[np.linalg.norm(t[arm][:, [0, 2]] - (sh + np.array([0.02, 0, 0]))[[0, 2]], axis=1) < 0.03]
    table.add_left(
        "acromion", r.extreme(cand, UP, "acromion"), "top of the shoulder, 2 cm lateral of the shoulder joint"
    )
    upper_axis = _unit(el - sh)
    fore_axis = _unit(wr - el)
    elbow_reg = r.near(r.region("shoulder_l", "elbow_l"), el, 0.07)
    table.add_left(
        "olecranon",
        r.extreme(elbow_reg, -FRONT, "olecranon"),
        "elbow point: most posterior point near the elbow joint",
    )
    eslab = r.slab(elbow_reg, el, upper_axis, 0.012)
    lat = r.lateral_dir(upper_axis)
    table.add_left(
        "humeral_lat_epicondyle",
        r.extreme(eslab, lat, "lat epicondyle"),
        "lateral extreme at the elbow joint level",
    )
    table.add_left(
        "humeral_med_epicondyle",
        r.extreme(eslab, -lat, "med epicondyle"),
        "medial extreme at the elbow joint level",
    )
    hand = r.region("wrist_l")
    tip = int(hand[np.argmax(np.linalg.norm(t[hand] - wr, axis=1))])
    hand_axis = _unit(t[tip] - wr)
    length = (t[tip] - wr) @ hand_axis
    along = (t[hand] - wr) @ hand_axis
    off_axis = t[hand] - wr - along[:, None] * hand_axis
    mid_hand = (along > 0.25 * length) & (along < 0.6 * length)
    thumb = int(hand[mid_hand][np.argmax(np.linalg.norm(off_axis[mid_hand], axis=1))])
    radial = _unit(off_axis[hand == thumb][0])
    wrist_reg = r.near(r.region("elbow_l", "wrist_l"), wr, 0.06)
    wslab = r.slab(wrist_reg, wr, fore_axis, 0.01)
    table.add_left(
        "radial_styloid",
        r.extreme(wslab, radial, "radial styloid"),
        "thumb-side extreme of the wrist at the wrist joint",
    )
    table.add_left(
        "ulnar_styloid",
        r.extreme(wslab, -radial, "ulnar styloid"),
        "little-finger-side extreme of the wrist at the wrist joint",
    )
    knuckles = hand[(np.abs(along - 0.42 * length) < 0.008)]
    knuckles = knuckles[np.linalg.norm(t[knuckles] - t[thumb], axis=1) > 0.035]
    table.add_left(
        "mcp2",
        r.extreme(knuckles, radial, "mcp2"),
        "index knuckle: thumb-side extreme at 42 % of the hand length (thumb excluded)",
    )
    table.add_left(
        "mcp5", r.extreme(knuckles, -radial, "mcp5"), "little-finger knuckle: other extreme at the same level"
    )
    table.add_left("dactylion", tip, "middle fingertip: hand vertex farthest from the wrist joint")
    table.add_left("thumb_tip", thumb, "thumb tip: hand point farthest from the hand axis, 25-60 % along it")


def _leg_left(r: _Rules, table: _Table) -> None:
    """Knee, ankle and foot on the left."""
    t = r.t
    hip = r.h("hip_l")
    kn, an = r.h("knee_l"), r.h("ankle_l")
    thigh_axis = _unit(kn - hip)
    shin_axis = _unit(an - kn)
    knee_reg = r.near(r.region("hip_l", "knee_l"), kn, 0.08)
    kslab = r.slab(knee_reg, kn, thigh_axis, 0.012)
    lat = r.lateral_dir(thigh_axis)
    table.add_left(
        "femoral_lat_epicondyle",
        r.extreme(kslab, lat, "femoral lat"),
        "lateral extreme at the knee joint level",
    )
    table.add_left(
        "femoral_med_epicondyle",
        r.extreme(kslab, -lat, "femoral med"),
        "medial extreme at the knee joint level",
    )
    table.add_left(
        "patella",
        r.extreme(r.slab(knee_reg, kn, thigh_axis, 0.02), FRONT, "patella"),
        "kneecap: most anterior point at the knee joint level",
    )
    tslab = r.slab(knee_reg, kn + 0.03 * shin_axis, shin_axis, 0.008)
    table.add_left(
        "tibiale",
        r.extreme(tslab, -r.lateral_dir(shin_axis), "tibiale"),
        "medial tibial condyle: medial extreme 3 cm below the knee joint",
    )
    ankle_reg = r.near(r.region("knee_l", "ankle_l"), an, 0.07)
    aslab = r.slab(ankle_reg, an, UP, 0.008)
    table.add_left(
        "lateral_malleolus",
        r.extreme(aslab, X_POS, "lat malleolus"),
        "lateral extreme at the ankle joint height",
    )
    table.add_left(
        "medial_malleolus",
        r.extreme(aslab, -X_POS, "med malleolus"),
        "medial extreme at the ankle joint height",
    )
    sslab = r.slab(ankle_reg, an - np.array([0.0, 0.02, 0.0]), UP, 0.006)
    sslab = sslab[t[sslab, 2] > an[2]]
    table.add_left(
        "sphyrion",
        r.extreme(sslab, -X_POS, "sphyrion"),
        "medial extreme 2 cm below the ankle joint, front half",
    )
    foot = r.region("ankle_l")
    low = foot[t[foot, 1] < t[foot, 1].min() + 0.03]
    heel = r.extreme(low, -FRONT, "heel")
    table.add_left("heel", heel, "calcaneus posterior: most posterior foot point within 3 cm of the sole")
    toe = r.extreme(foot, FRONT, "toe_tip")
    table.add_left("toe_tip", toe, "tip of the longest toe: most anterior foot point")
    flen = t[toe, 2] - t[heel, 2]
    table.add_left(
        "mtp1",
        r.extreme(r.band(low, 2, t[heel, 2] + 0.72 * flen, 0.008), -X_POS, "mtp1"),
        "ball of the big toe: medial extreme near the sole at 72 % of the foot length",
    )
    table.add_left(
        "mtp5",
        r.extreme(r.band(low, 2, t[heel, 2] + 0.63 * flen, 0.008), X_POS, "mtp5"),
        "ball of the little toe: lateral extreme near the sole at 63 % of the foot length",
    )


def _keypoint(model, name: str) -> np.ndarray:
    """Rest position (3,) of one of the model's surface keypoints."""
    k = list(model.keypoint_names).index(name)
    verts = model.keypoint_vertices[k].cpu().numpy()
    w = model.keypoint_weights[k].cpu().numpy().astype(np.float64)
    return (model.template.detach().cpu().numpy().astype(np.float64)[verts] * w[:, None]).sum(0)


def to_yaml(landmarks: list[Landmark]) -> str:
    """The ``landmarks.yaml`` text: ``name: {vertex: i}  # comment``, one landmark per line."""
    lines = [
        "# CAESAR-like anatomical landmarks on the packaged BLSM template (blsm/data/blsm_anny_v1.npz).",
        "# Generated by `python -m blsm.learn.scans.landmarks` from the rules in blsm/learn/scans/landmarks.py;",
        "# do not edit by hand. Each entry is {vertex: i} or {face: f, bary: [a, b, c]}.",
        "# Suffix _l / _r: the body's left (+X) / right; no suffix: on the midline x = 0.",
    ]
    for lm in landmarks:
        lines.append(f"{lm.name}: {{vertex: {lm.vertex}}}  # {lm.comment}")
    return "\n".join(lines) + "\n"


def render_landmarks(model, path: str | Path, landmarks: list[Landmark] | None = None) -> Path:
    """Front, side and back views of the template with the landmarks as coloured dots (PNG).

    Left landmarks are blue, right red, midline green; occluded dots are drawn smaller.
    """
    from PIL import Image, ImageDraw

    from blsm import render
    from blsm.camera import auto_camera

    lms = compute_landmarks(model) if landmarks is None else landmarks
    t = model.template.detach().cpu().numpy().astype(np.float64)
    f = model.faces.cpu().numpy()
    pts = t[[lm.vertex for lm in lms]]
    w, h = 420, 620
    tiles = []
    for az in (0.0, 90.0, 180.0):
        cam = auto_camera([(t, f)], w, h, azimuth_deg=az, elevation_deg=5.0)
        img = render.render_meshes([(t, f)], cam, spp=8)
        tile = Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8))
        draw = ImageDraw.Draw(tile)
        depth = cam.world_to_camera(t)[:, 2]
        uv_all = cam.project(t)
        for lm, (u, v), p in zip(lms, cam.project(pts), cam.world_to_camera(pts)[:, 2], strict=True):
            # Visible if no vertex projects within 3 px and is clearly in front of it.
            close = np.linalg.norm(uv_all - np.array([u, v]), axis=1) < 3.0
            hidden = bool((depth[close] < p - 0.03).any())
            col = (
                (0, 160, 0)
                if not lm.name.endswith(("_l", "_r"))
                else ((30, 60, 230) if lm.name.endswith("_l") else (220, 30, 30))
            )
            rad = 1.5 if hidden else 3.0
            draw.ellipse([u - rad, v - rad, u + rad, v + rad], fill=col, outline=(0, 0, 0))
        tiles.append(tile)
    sheet = Image.new("RGB", (w * len(tiles), h), (255, 255, 255))
    for i, tile in enumerate(tiles):
        sheet.paste(tile, (i * w, 0))
    return render.save_png(np.asarray(sheet), path)


def main(argv: list[str] | None = None) -> int:
    """``python -m blsm.learn.scans.landmarks [--out YAML] [--png PNG]``: rewrite ``blsm/data/landmarks.yaml``
    from the rules on the packaged rig's template (a maintainer's tool, not a ``blsm`` command)."""
    import argparse
    import sys

    import blsm
    from blsm.io import atomic_write
    from blsm.model import DEFAULT_RIG

    parser = argparse.ArgumentParser(prog="python -m blsm.learn.scans.landmarks", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=LANDMARKS_YAML, help="YAML file to write")
    parser.add_argument("--png", type=Path, default=None, help="also render the landmarks to this PNG")
    args = parser.parse_args(argv)
    model = blsm.load(DEFAULT_RIG)  # landmarks are defined on the rig's template
    lms = compute_landmarks(model)
    with atomic_write(args.out, "w") as fh:
        fh.write(to_yaml(lms))
    print(f"wrote {len(lms)} landmarks to {args.out}", file=sys.stderr)
    if args.png is not None:
        print(f"wrote {render_landmarks(model, args.png, lms)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
