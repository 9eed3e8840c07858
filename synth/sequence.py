"""Sequences: people playing motion clips in one world frame, filmed by a camera path (docs/video.md).

A sequence of ``T`` frames at ``F`` fps (``sequence.frames``, ``sequence.fps``) is made by one worker
from its own random generator (:func:`sequence_rng`), in this order:

1. **People.** Each draws a subject not yet in the clip (:func:`synth.people.draw_subject`), a
   motion-library clip (children: ``poses.child_clips`` when set) and a window of it without a cut
   (:func:`clip_segments`: a root or joint-angle jump), a heading (yaw about +Y, uniform) and
   plays the window from its start: the pose is interpolated between the clip's frames (a
   Catmull-Rom spline through the joint angles, kept inside their limits, and the root translation,
   so velocities are continuous; spherically in the root orientation).
   The root's path is the clip's, turned by the heading, scaled by the subject's leg length over the
   mean body's (the clip is retargeted to the mean body) and started at the origin.
2. **The body is posed** at every frame and one frame before the first and after the last,
   ``t_k = k / F`` for ``k = -1 .. T``, so that central differences (velocities and contact) exist
   at every frame, the first and last included. **Grounding**: retargeted mocap floats and sinks by a few
   centimetres from step to step, so the body is lifted per grid row: where a foot region (heel
   or toe) is still (its lowest vertex slower than ``contact.speed``), by what puts the stillest
   foot's lowest point on the ground ``y = 0``; between still phases (flight, a jump) the lift is
   interpolated linearly, so jumps stay jumps; the lift is smoothed over ``STANCE_SMOOTHING_S``
   and raised where a moving foot would dip more than ``PENETRATION_M`` under the ground. A clip
   without a still foot is lifted by one constant, its lowest point over the clip on the ground.
3. **Placement.** People are moved apart horizontally so that at every frame their footprint discs
   (the centre and radius of the body's hull in x-z, hair included) are ``people.gap`` apart: their
   trajectories never bring two bodies into one place at one time (they may cross a place at
   different times).
4. **Camera and light.** A camera path (:mod:`synth.camera_paths`) that keeps
   ``CAMERA_CLEARANCE_M`` from every body at every frame (drawn again until it does), one
   background, exposure and environment rotation for the whole clip.
5. **Frames.** Each frame is rendered and labelled as a single image is (:class:`synth.sample.SampleMaker`),
   plus the sequence's labels (docs/video.md): the camera-to-world transform and path, each
   person's ``track``, ``velocity_3d``, ``contact``, ``contact_velocity`` and ``in_view``. With
   ``sequence.motion_blur`` the image is the mean of sub-frame renders over the shutter (people and
   camera where they are at each sub-frame's time); the labels are the centre sub-frame's.

Contact (:func:`contact`): a region (:data:`CONTACT_REGIONS`) touches the ground when one of its
vertices is within ``sequence.contact.distance`` of ``y = 0`` and slower than ``contact.speed``.
Exact, because the ground is ours. Beside it, ``contact_velocity`` is the rule the field derives
contact with from motion capture: the region's point slower than ``contact.velocity_rule``. The
point is the region's keypoint (:data:`REGION_KEYPOINT`), but for the toes the toe base
(:func:`toe_base`): the point WHAM, GVHMR and HuMoR take (SMPL's foot joint) and the gait lab's toe
marker (on the second metatarsal head), where the toe tip is a point nobody measures.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from synth.camera import outline_index
from synth.camera_paths import Track, choose_kind, focal_mm, sample_path
from synth.dataset.format import CONTACT_REGIONS
from synth.people import draw_subject, footprint
from synth.sample import Person, Scene

REGION_KEYPOINT = {"heel_l": "heel_l", "heel_r": "heel_r", "toe_l": "toe_tip_l", "toe_r": "toe_tip_r",
                   "hand_l": "wrist_l", "hand_r": "wrist_r", "knee_l": "knee_l", "knee_r": "knee_r",
                   "pelvis": "pelvis"}  # fmt: skip
RULE_POINT = {**REGION_KEYPOINT, "toe_l": "toe_base_l", "toe_r": "toe_base_r"}
"""The point ``contact_velocity`` follows per region (the label ``contact_rule.velocity_points``):
the region's keypoint, the toe base (:func:`toe_base`) for the toes."""
FEET = ("heel_l", "heel_r", "toe_l", "toe_r")
TOE_BASE = (0.63, 0.72)
"""The toe base (:func:`toe_base`) spans these fractions of the heel-to-toe-tip axis: the positions
of the landmarks mtp5 and mtp1 (``blsm/data/landmarks.yaml``), the metatarsal heads."""
MAX_ROOT_SPEED = 8.0
"""m/s: a clip whose root moves faster between two frames has a cut there (CMU files often start
with a calibration frame at the origin); windows never cross one."""
STANCE_SMOOTHING_S = 0.05
"""Seconds: the standard deviation of the Gaussian that smooths the stance lift (step 2)."""
PENETRATION_M = 0.02
"""Metres: how far a moving foot may dip under the ground (a retargeting error of the clip) before
the body is raised; still feet are put on it."""
MAX_ANGLE_SPEED_DEG = 1500.0
"""Degrees a second: a joint angle changing faster between two frames of a clip is a cut (CMU's
dances hold atoms that flip between their limits, 95 degrees in a frame, in up to 1 % of frames;
walking peaks near 1000 degrees a second)."""
CAMERA_CLEARANCE_M = 0.5
"""Metres: a camera path passes no person's body (hull vertices) closer than this at any frame; a
path that would is drawn again (its kind kept) up to ``PATH_TRIES`` times, then replaced by a
static camera, which frames everyone from outside (``camera.path.tries`` records the draws)."""
PATH_TRIES = 20
KNEE_RADIUS = 0.1
"""Metres: the knee region is the shank's vertices this close to the knee joint."""


def sequence_rng(seed: int, sequence: int) -> np.random.Generator:
    """The random generator of sequence ``sequence``: a function of ``(seed, sequence)`` only."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), int(sequence), 1])))


def needed_seconds(cfg: Any) -> float:
    """Seconds of clip a sequence plays (``cfg``: :class:`synth.config.SequenceConfig`): its frames'
    span plus, either side, a frame (the central differences) or half the shutter (motion blur)."""
    blur = cfg.motion_blur.shutter / (2 * cfg.fps) if cfg.motion_blur.enabled else 0.0
    return (cfg.frames - 1) / cfg.fps + 2 * max(1.0 / cfg.fps, blur)


def clip_segments(clip: Any, limits: np.ndarray | None = None) -> list[tuple[int, int]]:
    """``[(first, last)]`` frame ranges of a clip without a cut: the root faster than
    :data:`MAX_ROOT_SPEED` between two frames, or (with the model's ``limits`` (47, 2), radians) a
    joint angle faster than :data:`MAX_ANGLE_SPEED_DEG` (an atom flipping between its limits, a
    retargeting glitch: a flicker in a video)."""
    fps = float(clip.fps)
    jump = np.linalg.norm(np.diff(clip.transl, axis=0), axis=1) * fps > MAX_ROOT_SPEED
    if limits is not None:
        lim = np.asarray(limits, np.float64)
        angles = 0.5 * (lim[:, 1] - lim[:, 0]) * np.tanh(np.asarray(clip.pose, np.float64))  # Eq. 6, less the midpoint
        jump |= np.degrees(np.abs(np.diff(angles, axis=0))).max(1) * fps > MAX_ANGLE_SPEED_DEG
    cuts = np.nonzero(jump)[0]
    edges = [0, *(cuts + 1).tolist(), len(clip.transl)]
    return [(a, b - 1) for a, b in zip(edges[:-1], edges[1:], strict=False) if b - 1 > a]


@dataclass(frozen=True)
class Window:
    """A window of a clip, played from ``start`` seconds into the clip."""

    clip: Any
    start: float

    def at(self, tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """``(x, global_orient, transl, clip frame)`` at ``tau`` seconds from the window's start."""
        from scipy.spatial.transform import Rotation

        c = self.clip
        q = (self.start + tau) * c.fps
        i = min(int(math.floor(q)), c.num_frames - 2)
        a = float(q - i)
        # The spline runs through the joint angles (Eq. 6: angle = mid + half tanh(x), so tanh(x)),
        # kept inside the limits: in x itself, a saturated atom's large jumps would overshoot.
        u = np.clip(
            _catmull_rom(np.tanh(c.pose[max(i - 1, 0) : i + 3].astype(np.float64)), min(i, 1), a),
            -1 + 1e-6,
            1 - 1e-6,
        )
        x, tr = np.arctanh(u), _catmull_rom(c.transl, i, a)
        r0, r1 = Rotation.from_rotvec(c.global_orient[i]), Rotation.from_rotvec(c.global_orient[i + 1])
        orient = (r0 * Rotation.from_rotvec(a * (r0.inv() * r1).as_rotvec())).as_rotvec()
        return x.astype(np.float32), orient, tr.astype(np.float64), q


def _catmull_rom(rows: np.ndarray, i: int, a: float) -> np.ndarray:
    """Rows ``i`` to ``i + 1`` of ``rows`` (T, D) at fraction ``a`` by the Catmull-Rom spline (the
    end rows repeated): through every row, with continuous velocity."""
    n = len(rows)
    p0, p1, p2, p3 = (rows[min(max(j, 0), n - 1)].astype(np.float64) for j in (i - 1, i, i + 1, i + 2))
    return 0.5 * (
        2 * p1 + a * (p2 - p0) + a * a * (2 * p0 - 5 * p1 + 4 * p2 - p3) + a**3 * (3 * p1 - p0 - 3 * p2 + p3)
    )


def draw_window(clips: list[Any], eligible: list[int], needed: float, rng: np.random.Generator,
                limits: np.ndarray | None = None) -> Window:
    """A window of ``needed`` seconds from one of the ``eligible`` clips (uniformly), inside a segment
    without a cut (segments weighted by the starts they allow), its start uniform."""
    ci = eligible[int(rng.integers(len(eligible)))]
    c = clips[ci]
    segs = [
        (a / c.fps, b / c.fps - needed)
        for a, b in clip_segments(c, limits)
        if (b - a) / c.fps >= needed
    ]
    w = np.array([hi - lo + 1e-9 for lo, hi in segs])
    lo, hi = segs[int(rng.choice(len(segs), p=w / w.sum()))]
    return Window(c, float(rng.uniform(lo, hi)))


def long_enough(clips: list[Any], needed: float, limits: np.ndarray | None = None) -> list[int]:
    """The clips with a segment of at least ``needed`` seconds."""
    return [
        i
        for i, c in enumerate(clips)
        if any((b - a) / c.fps >= needed for a, b in clip_segments(c, limits))
    ]


def eligible_clips(cfg: Any, clips: list[Any], limits: np.ndarray) -> list[int]:
    """The clips a sequence of ``cfg`` (:class:`synth.config.GeneratorConfig`) can play: a
    ValueError naming the motion library when none is long enough."""
    needed = needed_seconds(cfg.sequence)
    out = long_enough(clips, needed, limits)
    if not out:
        raise ValueError(f"{cfg.poses.library}: no clip holds {needed:.2f} s without a cut "
                         "(sequence.frames / sequence.fps); use fewer frames or longer clips")
    return out


def contact_regions(
    model: Any, vertex_bones: np.ndarray, vertices: np.ndarray, keypoints: np.ndarray
) -> dict[str, np.ndarray]:
    """Vertex indices of each contact region of a posed person (its own mesh): ``heel_*`` and
    ``toe_*`` split the foot bone's vertices at the middle of the heel-to-toe-tip axis, ``hand_*`` the
    hand bone's, ``knee_*`` the shank's within :data:`KNEE_RADIUS` of the knee, ``pelvis`` the
    pelvis bone's (sitting)."""
    bones, kp = list(model.bone_names), list(model.keypoint_names)
    out: dict[str, np.ndarray] = {}
    for s in ("l", "r"):
        foot, u = _foot_axis(model, vertex_bones, vertices, keypoints, s)
        out[f"heel_{s}"], out[f"toe_{s}"] = foot[u < 0.5], foot[u >= 0.5]
        out[f"hand_{s}"] = np.nonzero(vertex_bones == bones.index(f"wrist_{s}"))[0]
        shank = np.nonzero(vertex_bones == bones.index(f"knee_{s}"))[0]
        knee = keypoints[kp.index(f"knee_{s}")]
        out[f"knee_{s}"] = shank[np.linalg.norm(vertices[shank] - knee, axis=1) <= KNEE_RADIUS]
    out["pelvis"] = np.nonzero(vertex_bones == bones.index("pelvis"))[0]
    return {k: out[k] for k in CONTACT_REGIONS}


def toe_base(model: Any, vertex_bones: np.ndarray, vertices: np.ndarray, keypoints: np.ndarray) -> dict[str, np.ndarray]:
    """Vertex indices whose centroid is the toe base of each foot (``toe_l``, ``toe_r``) of a posed
    person: the foot bone's vertices between the fractions :data:`TOE_BASE` of the heel-to-toe-tip
    axis. Their centroid lies inside the foot at the metatarsal heads, where SMPL's foot joint is."""
    out = {}
    for s in ("l", "r"):
        foot, u = _foot_axis(model, vertex_bones, vertices, keypoints, s)
        out[f"toe_{s}"] = foot[(u >= TOE_BASE[0]) & (u <= TOE_BASE[1])]
    return out


def _foot_axis(
    model: Any, vertex_bones: np.ndarray, vertices: np.ndarray, keypoints: np.ndarray, side: str
) -> tuple[np.ndarray, np.ndarray]:
    """The foot bone's vertex indices on ``side`` (``"l"``, ``"r"``) and each one's position along
    the heel-to-toe-tip axis (0 at the heel keypoint, 1 at the toe tip)."""
    kp = list(model.keypoint_names)
    foot = np.nonzero(vertex_bones == list(model.bone_names).index(f"ankle_{side}"))[0]
    heel, toe = keypoints[kp.index(f"heel_{side}")], keypoints[kp.index(f"toe_tip_{side}")]
    return foot, (vertices[foot] - heel) @ (toe - heel) / max(float((toe - heel) @ (toe - heel)), 1e-12)


def contact(heights: np.ndarray, speeds: np.ndarray, distance: float, speed: float) -> bool:
    """A region touches the ground: one of its vertices (``heights`` above ``y = 0`` and ``speeds``,
    m/s) is within ``distance`` of it and slower than ``speed``."""
    return bool(((heights <= distance) & (speeds <= speed)).any())


def place_tracks(
    footprints: list[np.ndarray], gap: float, rng: np.random.Generator, tries: int = 400
) -> list[np.ndarray]:
    """Horizontal offsets (x, z) so that, at every frame, the people's footprint discs are ``gap``
    apart. ``footprints``: per person, (T, 3) rows ``(x, z, radius)``."""
    offsets: list[np.ndarray] = []
    for i, fp in enumerate(footprints):
        if i == 0:
            offsets.append(np.zeros(2))
            continue
        reach = 1.0 + max(float(f[:, 2].max()) for f in footprints[: i + 1])
        for n in range(tries):
            ang = rng.uniform(0, 2 * math.pi)
            rad = reach * (1.0 + 4.0 * n / tries) * math.sqrt(rng.uniform(0.25, 1.0))
            o = rad * np.array([math.cos(ang), math.sin(ang)])
            ok = all(
                (np.linalg.norm(fp[:, :2] + o - (footprints[j][:, :2] + offsets[j]), axis=1) >= fp[:, 2] + footprints[j][:, 2] + gap).all()
                for j in range(i)
            )  # fmt: skip
            if ok:
                offsets.append(o)
                break
        else:  # pragma: no cover - the reach grows to 5x: always found
            raise RuntimeError("could not place the people's trajectories apart")
    return offsets


@dataclass(eq=False)
class Actor:
    """One person of a sequence: a subject playing a window of a clip (module docstring, steps 1-3).

    Attributes:
        posed: seconds from the clip window's start -> the person posed there (not placed).
        frames: the ``T`` frames' posed people, placed by :meth:`SequenceMaker.make`.
        keypoints: (T + 2, K, 3) on the frame grid (one row before the first frame and one after
            the last); ``region_vertices`` region -> (T + 2, n, 3) its vertices there.
        rule_points: (T + 2, R, 3) the point of each region of :data:`CONTACT_REGIONS` that
            ``contact_velocity`` follows (module docstring), on the grid.
        lift: (T + 2,) metres each grid row is lifted by (grounding).
        window: the clip window (the label's ``clip_window``).
        offset: (3,) the placement's horizontal offset, metres (None before placement).
    """

    posed: Callable[[float], Person]
    frames: list[Person]
    keypoints: np.ndarray
    region_vertices: dict[str, np.ndarray]
    rule_points: np.ndarray
    lift: np.ndarray
    window: dict[str, Any]
    offset: np.ndarray | None = None


class SequenceMaker:
    """Makes the frames of sequences with a worker's :class:`synth.sample.SampleMaker`."""

    def __init__(self, maker: Any) -> None:
        import torch

        self.m = maker
        self.cfg = maker.cfg.sequence
        self.T, self.F = self.cfg.frames, float(self.cfg.fps)
        self.h = 1.0 / self.F
        self.needed = needed_seconds(self.cfg)
        self.margin = 0.5 * (self.needed - (self.T - 1) / self.F)
        poses = maker.poses
        self.limits = maker.model.dof_limits.numpy()
        self.eligible = eligible_clips(maker.cfg, poses.clips, self.limits)
        self.child_eligible = [i for i in self.eligible if i in poses.child_clips]
        model = maker.model
        with torch.no_grad():
            rest = model().rest_joints[0].numpy()
        self.bones, self.kp = list(model.bone_names), list(model.keypoint_names)
        self.mean_leg = self._leg(rest)
        self.region_kp = [self.kp.index(REGION_KEYPOINT[r]) for r in CONTACT_REGIONS]

    def _leg(self, rest_joints: np.ndarray) -> float:
        b = self.bones
        return float(
            np.mean(
                [rest_joints[b.index(f"hip_{s}"), 1] - rest_joints[b.index(f"ankle_{s}"), 1] for s in "lr"]
            )
        )

    # -- people
    def _person(self, rng: np.random.Generator, taken: list[int]) -> Actor:
        """One person's clip, posed on the frame grid (module docstring, steps 1-2); its subject is
        drawn (:func:`synth.people.draw_subject`) and appended to ``taken``, the clip's so far."""
        from scipy.spatial.transform import Rotation

        m = self.m
        si = draw_subject(rng, len(m.subjects), taken, m.cfg.people.distinct)
        taken.append(si)
        age = m.subjects[si].meta.get("phenotype", {}).get("age_years")
        child = age is not None and age < 18.0 and self.child_eligible
        win = draw_window(m.poses.clips, self.child_eligible if child else self.eligible, self.needed, rng, self.limits)
        yaw = float(rng.uniform(0, 2 * math.pi))
        turn = Rotation.from_rotvec([0.0, yaw, 0.0])
        start = win.at(0.0)[2]
        scale = None

        def posed(tau: float) -> Person:
            nonlocal scale
            x, orient, tr, q = win.at(tau)
            rel = tr - np.array([start[0], 0.0, start[2]])
            if scale is None:  # the subject's legs over the mean body's
                probe = m.pose(si, x, np.zeros(3, np.float32), np.zeros(3, np.float32))
                scale = self._leg(probe.rest_joints) / self.mean_leg
            world_orient = (turn * Rotation.from_rotvec(orient)).as_rotvec().astype(np.float32)
            p = m.pose(si, x, world_orient, (turn.apply(scale * rel)).astype(np.float32))
            p.motion = {"source": "library", "clip": win.clip.name, "frame": round(float(q), 4),
                        "time": round(float(q / win.clip.fps), 6)}  # fmt: skip
            return p

        grid = [posed(self.margin + k * self.h) for k in range(-1, self.T + 1)]  # k = -1 .. T
        first = grid[1]
        regions = contact_regions(m.model, first.vertex_bones, first.vertices, first.keypoints)
        region_vertices = {r: np.stack([g.vertices[idx] for g in grid]).astype(np.float64) for r, idx in regions.items()}
        keypoints = np.stack([g.keypoints for g in grid]).astype(np.float64)
        rule_points = keypoints[:, self.region_kp].copy()
        for r, idx in toe_base(m.model, first.vertex_bones, first.vertices, first.keypoints).items():
            rule_points[:, CONTACT_REGIONS.index(r)] = np.stack([g.vertices[idx].mean(0) for g in grid])
        frames = grid[1:-1]
        return Actor(
            posed=posed, frames=frames, keypoints=keypoints,
            region_vertices=region_vertices, rule_points=rule_points,
            lift=self._lift(grid, region_vertices),
            window={"clip": win.clip.name, "start_s": round(win.start + self.margin, 6), "yaw_deg": round(math.degrees(yaw), 4),
                    "leg_scale": round(float(scale), 6)},
        )  # fmt: skip

    def _lift(self, grid: list[Person], region_vertices: dict[str, np.ndarray]) -> np.ndarray:
        """The height (m) each grid row is lifted by (module docstring, step 2): where a foot is still,
        its lowest point on the ground; between, interpolated; then smoothed, and raised where a
        body would go more than :data:`PENETRATION_M` into the ground."""
        from scipy.ndimage import gaussian_filter1d

        lowest = np.array([float(g.vertices[:, 1].min()) for g in grid])
        heights, speeds = [], []
        for r in FEET:
            v = region_vertices[r]  # (N, n, 3), per grid row
            if v.shape[1] == 0:
                continue
            low = v[:, :, 1].argmin(1)
            pts = v[np.arange(len(v)), low]  # the region's lowest vertex, per row
            vel = np.gradient(v, self.h, axis=0)[np.arange(len(v)), low]
            heights.append(pts[:, 1])
            speeds.append(np.linalg.norm(vel, axis=1))
        h, sp = np.array(heights), np.array(speeds)
        still = sp <= self.cfg.contact.speed
        ground = np.where(still, h, np.inf).min(0)  # the stillest feet's lowest point, per row
        rows = np.nonzero(np.isfinite(ground))[0]
        if len(rows) == 0:  # no foot ever still (a clip in the air): the clip's lowest point on the ground
            return np.full(len(grid), -lowest.min())
        lift = np.interp(np.arange(len(grid)), rows, -ground[rows])
        lift = gaussian_filter1d(lift, STANCE_SMOOTHING_S / self.h, mode="nearest")
        return np.maximum(lift, -lowest - PENETRATION_M)

    # -- a sequence
    def make(self, seq: int, rng: np.random.Generator) -> list[dict[str, bytes]]:
        """The ``T`` frames of sequence ``seq``: each frame's fields, in order."""
        m, cfg, T, F = self.m, self.m.cfg, self.T, self.F
        n = int(rng.integers(cfg.people.min, cfg.people.max + 1))
        taken: list[int] = []
        people = [self._person(rng, taken) for _ in range(n)]
        footprints = []
        for p in people:
            rows = []
            for fr in p.frames:
                v = fr.shell()
                fr.outline = v[outline_index(v)].astype(np.float32)
                c, r = footprint(fr.outline)
                rows.append([c[0], c[1], r])
            footprints.append(np.array(rows))
        offsets = place_tracks(footprints, cfg.people.gap, rng)
        for p, o in zip(people, offsets, strict=False):
            p.offset = np.array([o[0], 0.0, o[1]])
            rows = p.offset + np.outer(p.lift, [0.0, 1.0, 0.0])  # (T + 2, 3) per grid row
            for f, fr in enumerate(p.frames):
                fr.move(rows[f + 1])
            p.keypoints += rows[:, None]
            p.rule_points += rows[:, None]
            for r in p.region_vertices:
                p.region_vertices[r] += rows[:, None]
        step = max(1, T // 24)
        everyone = np.concatenate(
            [p.frames[f].outline for p in people for f in [*range(0, T, step), T - 1]]
        )
        follow = Track(
            np.arange(T) / F,
            np.array([0.5 * (fr.outline.min(0) + fr.outline.max(0)) for fr in people[0].frames]),
        )
        kind = choose_kind(self.cfg.cameras.weights(), rng)
        tries = 0
        while True:
            tries += 1
            if tries > PATH_TRIES:  # a tripod framing everyone from outside them
                kind = "static"
            path = sample_path(kind, cfg.camera, self.cfg.cameras, everyone, people[0].frames[0].outline, follow,
                               (T - 1) / F, rng)  # fmt: skip
            if tries > PATH_TRIES or self._clear(path, people):
                break
        path.params["tries"] = tries
        back = m.background(rng, path.at(0.0))
        return [self._frame(seq, f, people, path, back, rng) for f in range(T)]

    def _clear(self, path: Any, people: list[Actor]) -> bool:
        """The camera keeps :data:`CAMERA_CLEARANCE_M` from every person's hull at every frame."""
        for f in range(self.T):
            cam = path.at(f / self.F)
            eye = -cam.R.T @ cam.t
            for p in people:
                if np.linalg.norm(p.frames[f].outline - eye, axis=1).min() < CAMERA_CLEARANCE_M:
                    return False
        return True

    def _labels(self, p: Actor, f: int) -> dict[str, Any]:
        """Velocities and contact of person ``p`` at frame ``f`` (central differences on the grid)."""
        k = f + 1  # the frame's row on the grid (row 0 is k = -1)
        kp = p.keypoints
        vel = (kp[k + 1] - kp[k - 1]) / (2 * self.h)
        c = self.cfg.contact
        touch, rule = {}, {}
        rule_speed = np.linalg.norm(p.rule_points[k + 1] - p.rule_points[k - 1], axis=1) / (2 * self.h)
        for i, r in enumerate(CONTACT_REGIONS):
            rv = p.region_vertices[r]
            speeds = np.linalg.norm(rv[k + 1] - rv[k - 1], axis=1) / (2 * self.h)
            touch[r] = contact(rv[k][:, 1], speeds, c.distance, c.speed) if len(rv[k]) else False
            rule[r] = bool(rule_speed[i] <= c.velocity_rule)
        return {"velocity_3d": vel, "contact": touch, "contact_velocity": rule}

    def _frame(
        self, seq: int, f: int, people: list[Actor], path: Any, back: Any, rng: np.random.Generator
    ) -> dict[str, bytes]:
        from synth.dataset.format import json_round as _l

        m, T, F = self.m, self.T, self.F
        index = seq * T + f
        t = f / F
        camera = path.at(t)
        frame_people = [p.frames[f] for p in people]
        cam_info = {**path.base, "view": "normal", "truncated": False, "truncation": 0.0, "truncation_side": "",
                    "focal_mm": round(focal_mm(camera), 6), "path": path.kind}  # fmt: skip
        scene = Scene(index, frame_people, camera, cam_info, back)
        blur = self.cfg.motion_blur
        if blur.enabled and blur.subframes > 1:
            rgb = None
            offsets = [(j / (blur.subframes - 1) - 0.5) * blur.shutter / F for j in range(blur.subframes)]
            offsets = [o for o in offsets if o != 0.0]
            for o in offsets:  # the other sub-frames first; the centre's render gives the labels
                sub_people = [self._posed_at(p, t + o) for p in people]
                fr_o, _ = m.render_frame(Scene(index, sub_people, path.at(t + o), cam_info, back), rng)
                rgb = fr_o.rgb if rgb is None else rgb + fr_o.rgb
            frame, labels = m.render_frame(scene, rng)
            frame.rgb = ((rgb + frame.rgb) / blur.subframes).astype(np.float32)
        else:
            frame, labels = m.render_frame(scene, rng)
        c = self.cfg.contact
        to_world = np.eye(4)
        to_world[:3, :3], to_world[:3, 3] = camera.R.T, -camera.R.T @ camera.t
        extra = {"sequence": seq, "frame": f, "frames": T, "fps": F, "time": round(t, 9),
                 "camera": {"to_world": _l(to_world), "path": _json(path.info)},
                 "contact_rule": {"distance": c.distance, "speed": c.speed, "velocity_rule": c.velocity_rule,
                                  "velocity_points": RULE_POINT},
                 **({"motion_blur": {"subframes": blur.subframes, "shutter": blur.shutter}} if blur.enabled else {})}  # fmt: skip
        extra_people = []
        for i, (p, lp) in enumerate(zip(people, labels["people"], strict=False)):
            sl = self._labels(p, f)
            extra_people.append({"track": i, "velocity_3d": _l(sl["velocity_3d"]), "contact": sl["contact"],
                                 "contact_velocity": sl["contact_velocity"], "in_view": bool(lp["pixels"] > 0),
                                 "clip_window": p.window})  # fmt: skip
        scene.extra = extra
        return m.encode(scene, frame, labels, extra_people)

    def _posed_at(self, p: Actor, t: float) -> Person:
        """Person ``p`` posed at time ``t`` of the sequence (a motion-blur sub-frame), placed."""
        q = p.posed(self.margin + t)
        lift = float(np.interp(t, (np.arange(len(p.lift)) - 1) * self.h, p.lift))
        q.move(p.offset + np.array([0.0, lift, 0.0]))
        v = q.shell()
        q.outline = v[outline_index(v)].astype(np.float32)
        return q


def _json(obj: Any) -> Any:
    """Floats rounded to 1e-6 in nested lists, tuples and dicts (stable JSON)."""
    if isinstance(obj, dict):
        return {k: _json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json(v) for v in obj]
    if isinstance(obj, float):
        return round(obj, 6)
    return obj
