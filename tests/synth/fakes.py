"""A small fake dataset in the sample format of :mod:`synth.dataset.format`, made without Mitsuba.

Each sample holds one or two BLSM people posed at random and seen by an OpenCV camera whose
principal point is off centre. The labels follow the format exactly: keypoints are the model's,
projected with :meth:`blsm.camera.Camera.project`; the parts map is thick strokes along the bones
(one label per bone's part, left/right the person's own), the mask is where a person's strokes are
(person 0 in front); the image is the dimmed part colours on grey with a ``DOT`` x ``DOT`` square of
colour :func:`dot_colour` ``(k)`` centred on the pixel of every in-frame keypoint ``k`` of person 0.

Sample 1 has a second person far out of frame (no pixels, ``box`` None), samples 3, 5, ... one
person, the others two.

:func:`write_fake_sequences` writes a fake *video* dataset in the layout of ``docs/video.md`` with
the same drawing: see its docstring.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image, ImageDraw

import blsm
from blsm import skeleton
from blsm.camera import Camera, look_at_camera
from synth.dataset import format as fmt
from synth.dataset.format import CONTACT_REGIONS
from synth.sequence import REGION_KEYPOINT
from synth.dataset.shards import ShardWriter

DOT = 7
BACKGROUND = 40


def dot_colour(k: int) -> np.ndarray:
    """(3,) uint8 colour of keypoint ``k``'s dot: distinct per keypoint and from the parts' colours."""
    return np.array([64 + 4 * k, 255 - 4 * k, 200], dtype=np.uint8)


def _strokes(model: blsm.BLSM) -> list[tuple[str, str, int]]:
    """(from keypoint, to keypoint, part label) for every bone and leaf segment."""
    out = []
    for j, par in enumerate(skeleton.BONE_PARENTS):
        if par >= 0:
            out.append((skeleton.BONE_NAMES[par], skeleton.BONE_NAMES[j], 1 + skeleton.BONE_PARTS[par]))
    part = {n: 1 + p for n, p in zip(skeleton.BONE_NAMES, skeleton.BONE_PARTS, strict=True)}
    for a, b in (("head", "head_top"), ("wrist_l", "hand_tip_l"), ("wrist_r", "hand_tip_r")):
        out.append((a, b, part[a]))
    for a, b in (("ankle_l", "toe_tip_l"), ("ankle_r", "toe_tip_r")):
        out.append((a, b, part[a]))
    return out


def _draw(
    model: blsm.BLSM, uvs: list[np.ndarray], size: tuple[int, int], stroke: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The image (H, W, 3), mask (H, W) and parts (H, W) of people with keypoint pixels ``uvs``."""
    w, h = size
    names = model.keypoint_names
    mask = np.zeros((h, w), np.uint8)
    parts = np.zeros((h, w), np.uint8)
    for p in reversed(range(len(uvs))):  # person 0 last: in front
        layer = Image.new("L", (w, h), 0)
        draw = ImageDraw.Draw(layer)
        for a, b, label in _strokes(model):
            ua, ub = uvs[p][names.index(a)], uvs[p][names.index(b)]
            # PIL puts pixel centres at integers
            draw.line([tuple(ua - 0.5), tuple(ub - 0.5)], fill=label, width=stroke)
        lab = np.asarray(layer)
        parts = np.where(lab > 0, lab, parts)
        mask = np.where(lab > 0, p + 1, mask).astype(np.uint8)
    rgb = np.where(parts[..., None] > 0, fmt.PART_PALETTE[parts] // 2, BACKGROUND).astype(np.uint8)
    r = DOT // 2
    for k, (u, v) in enumerate(np.floor(uvs[0]).astype(int)):
        if 0 <= u < w and 0 <= v < h:
            rgb[max(v - r, 0) : v + r + 1, max(u - r, 0) : u + r + 1] = dot_colour(k)
    return rgb, mask, parts


def _person(
    p: int,
    q: dict[str, Any],
    angles: np.ndarray,
    kp: np.ndarray,
    cam: Camera,
    mask: np.ndarray,
    rng: np.random.Generator,
) -> dict[str, Any]:
    """The labels of person ``p`` (BLSM parameters ``q``, world keypoints ``kp`` (K, 3))."""
    h, w = mask.shape
    uv, kc = cam.project(kp), cam.world_to_camera(kp)
    px = np.floor(uv).astype(int)
    in_frame = (kc[:, 2] > 0) & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    visible = in_frame.copy()
    for k in np.flatnonzero(in_frame):
        visible[k] = mask[px[k, 1], px[k, 0]] == p + 1 and rng.uniform() > 0.1
    ys, xs = np.nonzero(mask == p + 1)
    box = [int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1] if len(xs) else None
    return {
        "subject": f"fake{p}",
        "pipeline": "blsm",
        "motion": {"source": "random", "clip": None, "frame": 0},
        "blsm": {
            "pose": q["pose"].tolist(),
            "angles": angles.tolist(),
            "bone": q["bone"].tolist(),
            "shape": q["shape"].tolist(),
            "global_orient": q["global_orient"].tolist(),
            "transl": q["transl"].tolist(),
        },
        "bone_lengths": [0.1] * len(skeleton.BONE_NAMES),
        "keypoints_3d": kp.tolist(),
        "keypoints_3d_cam": kc.tolist(),
        "keypoints_2d": uv.tolist(),
        "visible": visible.tolist(),
        "in_frame": in_frame.tolist(),
        "box": box,
        "box_full": [*(uv.min(0) - 5).tolist(), *(uv.max(0) + 5).tolist()],
        "pixels": int(len(xs)),
    }


def _doc(index: int, cam: Camera, model: blsm.BLSM, people: list[dict[str, Any]]) -> dict[str, Any]:
    return {
        "format": fmt.FORMAT,
        "version": fmt.VERSION,
        "index": index,
        "seed": 0,
        "image": {"width": cam.width, "height": cam.height, "pixel_center": 0.5},
        "camera": {"K": cam.K.tolist(), "R": cam.R.tolist(), "t": cam.t.tolist(), "info": {"fake": True}},
        "background": {"kind": "flat", "value": BACKGROUND},
        "keypoint_names": list(model.keypoint_names),
        "bone_names": list(model.bone_names),
        "part_names": list(model.part_names),
        "people": people,
    }


def _members(doc: dict[str, Any], rgb: np.ndarray, mask: np.ndarray, parts: np.ndarray) -> dict[str, bytes]:
    h, w = mask.shape
    return {
        "rgb.png": fmt.encode_png(rgb),
        "json": fmt.encode_json(doc),
        "mask.png": fmt.encode_png(mask),
        "parts.png": fmt.encode_png(parts, fmt.PART_PALETTE),
        "bones.png": fmt.encode_png(np.zeros((h, w), np.uint8), fmt.BONE_PALETTE),
        "depth.exr": fmt.encode_exr(np.zeros((h, w), np.float32)),
        "corr.npy.gz": fmt.encode_npy_gz(np.full((h, w, 3), -1.0, np.float32)),
    }


def _pose(model: blsm.BLSM, params: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """World keypoints (B, K, 3) and angles (B, 47) of the batch of BLSM parameters ``params``."""
    with torch.no_grad():
        out = model(**{k: torch.tensor(v, dtype=torch.float32) for k, v in params.items()})
    return out.keypoints.double().numpy(), out.angles.double().numpy()


def make_sample(
    index: int, rng: np.random.Generator, model: blsm.BLSM, size: tuple[int, int]
) -> dict[str, bytes]:
    """All members of fake sample ``index`` (``size`` is (width, height))."""
    w, h = size
    n_people = 1 if index % 2 == 1 and index != 1 else 2
    offsets = [np.zeros(3), np.array([10.0 if index == 1 else 0.6, 0.0, -1.0])]  # 10 m: out of frame
    params = []
    for p in range(n_people):
        yaw_tilt = [rng.normal(0, 0.1), rng.uniform(-np.pi, np.pi), rng.normal(0, 0.1)]
        params.append(
            {
                "pose": rng.normal(0.0, 0.6, 47),
                "bone": rng.normal(0.0, 0.5, model.num_bone_coeffs),
                "shape": rng.normal(0.0, 0.5, model.num_shape_coeffs),
                "global_orient": np.array(yaw_tilt),
                "transl": offsets[p],
            }
        )
    kps, angles = _pose(model, {k: np.stack([q[k] for q in params]) for k in params[0]})
    pelvis = kps[0, 0]
    eye = pelvis + [rng.uniform(-0.5, 0.5), 0.3, 3.0]
    cam = look_at_camera(eye, pelvis, up=(0.1, 1.0, 0.0), fov_y_deg=50, width=w, height=h)
    kmat = cam.K.copy()
    kmat[0, 2] += 7.3
    kmat[1, 2] -= 4.1
    cam = Camera(K=kmat, R=cam.R, t=cam.t, width=w, height=h)
    rgb, mask, parts = _draw(model, [cam.project(kp) for kp in kps], size, 9)
    people = [_person(p, q, angles[p], kps[p], cam, mask, rng) for p, q in enumerate(params)]
    return _members(_doc(index, cam, model, people), rgb, mask, parts)


def make_dataset(
    out: str | Path,
    num: int = 6,
    shard_size: int = 3,
    seed: int = 0,
    size: tuple[int, int] = (256, 240),
    model: blsm.BLSM | None = None,
) -> Path:
    """Write a complete fake dataset folder (manifest and shards) and return its path."""
    model = blsm.load() if model is None else model
    writer = ShardWriter(out=Path(out), num=num, shard_size=shard_size, seed=seed, config={"fake": True})
    writer.run(lambda i, rng: make_sample(i, rng, model, size))
    return Path(out)


# ------------------------------------------------------------------------------------------------
# Video sequences


def _yaw(a: float) -> np.ndarray:
    """(3, 3) rotation by ``a`` radians about world Y."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _axis_angle(rot: np.ndarray) -> np.ndarray:
    """(B, 3, 3) rotations to (B, 3) axis-angle."""
    from kornia.geometry.conversions import rotation_matrix_to_axis_angle

    return rotation_matrix_to_axis_angle(torch.as_tensor(rot, dtype=torch.float64)).numpy()


class _FakeSequence:
    """The motion and camera path of one fake sequence: everything but the per-frame drawing.

    Person ``p`` keeps its bone and shape, walks a straight line at constant speed (person 0 slowly,
    0.1 m/s, so its feet are in contact; the others at 1 m/s, turning at 1 rad/s), its pose
    oscillating a little about a random one, feet on the ground (``y = 0``) at time 0. With ``exit``
    the last person of an odd sequence runs out of view to the right (fast: from 0.85 W to 1.6 W
    of the image over the sequence, whatever its duration). The camera pans about world Y.
    """

    def __init__(
        self,
        s: int,
        seed: int,
        model: blsm.BLSM,
        frames: int,
        fps: float,
        people: int,
        size: tuple[int, int],
        exit: bool,
    ) -> None:
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([seed, s, 0x5E0])))
        self.frames, self.fps, self.size = frames, fps, size
        w, h = size
        nk = len(model.keypoint_names)
        times = np.arange(frames) / fps
        dt = 1.0 / (2.0 * fps)
        when = np.concatenate([times, times - dt, times + dt])  # (3T,): now, t - h, t + h
        self.params: list[dict[str, np.ndarray]] = []  # per person: (T, ...) parameters
        kps = np.zeros((people, 3 * frames, nk, 3))
        self.angles = np.zeros((people, frames, 47))
        motion: list[tuple[np.ndarray, np.ndarray, float, float]] = []
        for p in range(people):
            start = np.array([0.7 * p * (-1) ** p, 0.0, -0.8 * p])
            yaw0 = rng.uniform(-np.pi, np.pi)
            speed, turn = (0.1, 0.0) if p == 0 else (1.0, 1.0)
            heading = rng.uniform(-np.pi, np.pi)
            vel = speed * np.array([math.sin(heading), 0.0, math.cos(heading)])
            motion.append((start, vel, yaw0, turn))
        # the camera: looking at person 0's start from about 3.5 m, panning at yaw_rate rad/s
        eye = np.array([rng.uniform(-0.5, 0.5), 1.3, 3.5])
        cam0 = look_at_camera(eye, np.array([0.0, 0.9, 0.0]), up=(0, 1, 0), fov_y_deg=50, width=w, height=h)
        yaw_rate = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 0.4))
        self.cameras = []
        for t in times:
            rot = cam0.R @ _yaw(yaw_rate * t).T  # camera-to-world rotated about Y through the eye
            self.cameras.append(Camera(K=cam0.K, R=rot, t=-rot @ eye, width=w, height=h))
        self.path = {"kind": "pan", "eye": eye.tolist(), "yaw_rate": yaw_rate, "fake": True}
        if exit and s % 2 == 1 and people > 1:
            # the last person: from u = 0.85 W to 1.6 W along the first camera's x axis at 4.5 m depth
            right = cam0.R[0] * np.array([1.0, 0.0, 1.0])
            right /= np.linalg.norm(right)
            depth, f = 4.5, cam0.K[0, 0]
            centre = eye + depth * cam0.R[2] * np.array([1.0, 0.0, 1.0]) / np.linalg.norm(cam0.R[2][[0, 2]])
            u0, u1 = (0.85 * w - cam0.K[0, 2]) * depth / f, (1.6 * w - cam0.K[0, 2]) * depth / f
            duration = max(times[-1], 1.0 / fps)
            start = centre + u0 * right
            start[1] = 0.0
            motion[-1] = (start, (u1 - u0) / duration * right, motion[-1][2], 0.0)
        for p, (start, vel, yaw0, turn) in enumerate(motion):
            base = rng.normal(0.0, 0.3, 47)
            swing, phase = rng.normal(0.0, 0.05, 47), rng.uniform(0, 2 * np.pi, 47)
            q = {
                "pose": base + swing * np.sin(2 * np.pi * 0.5 * when[:, None] + phase),
                "bone": np.tile(rng.normal(0.0, 0.5, model.num_bone_coeffs), (3 * frames, 1)),
                "shape": np.tile(rng.normal(0.0, 0.5, model.num_shape_coeffs), (3 * frames, 1)),
                "global_orient": _axis_angle(np.stack([_yaw(yaw0 + turn * t) for t in when])),
                "transl": start + when[:, None] * vel,
            }
            kp, ang = _pose(model, q)
            feet = [model.keypoint_names.index(n) for n in ("heel_l", "heel_r", "toe_tip_l", "toe_tip_r")]
            lift = -kp[0, feet, 1].min()  # feet on the ground at time 0
            q["transl"][:, 1] += lift
            kps[p] = kp + [0.0, lift, 0.0]
            self.angles[p] = ang[:frames]
            self.params.append({k: v[:frames] for k, v in q.items()})
        self.keypoints = kps[:, :frames]  # (P, T, K, 3)
        self.velocity = (kps[:, 2 * frames :] - kps[:, frames : 2 * frames]) / (2 * dt)  # (P, T, K, 3)
        self.contact_index = [model.keypoint_names.index(REGION_KEYPOINT[r]) for r in CONTACT_REGIONS]

    def contacts(self, p: int, f: int) -> tuple[dict[str, bool], dict[str, bool]]:
        """``contact`` (height < 0.05 m and speed < 0.2 m/s) and ``contact_velocity`` (height < 0.1
        m and speed < 0.3 m/s) of person ``p`` in frame ``f``, per region of ``CONTACT_REGIONS``."""
        height = self.keypoints[p, f, self.contact_index, 1]
        speed = np.linalg.norm(self.velocity[p, f, self.contact_index], axis=-1)
        geo = (height < 0.05) & (speed < 0.2)
        vel = (height < 0.1) & (speed < 0.3)
        return (
            {r: bool(c) for r, c in zip(CONTACT_REGIONS, geo, strict=True)},
            {r: bool(c) for r, c in zip(CONTACT_REGIONS, vel, strict=True)},
        )


def make_sequence_frame(
    s: int, f: int, seq: _FakeSequence, rng: np.random.Generator, model: blsm.BLSM
) -> dict[str, bytes]:
    """All members of frame ``f`` of fake sequence ``s``."""
    cam, n = seq.cameras[f], len(seq.params)
    stroke = max(3, round(9 * seq.size[0] / 256))
    rgb, mask, parts = _draw(model, [cam.project(seq.keypoints[p, f]) for p in range(n)], seq.size, stroke)
    people = []
    for p in range(n):
        q = {k: v[f] for k, v in seq.params[p].items()}
        lab = _person(p, q, seq.angles[p, f], seq.keypoints[p, f], cam, mask, rng)
        contact, contact_velocity = seq.contacts(p, f)
        time = f / seq.fps
        lab.update(
            track=p,
            motion={"source": "library", "clip": f"fake_{s}_{p}", "frame": float(f), "time": time},
            velocity_3d=seq.velocity[p, f].tolist(),
            contact=contact,
            contact_velocity=contact_velocity,
            in_view=lab["pixels"] > 0,
        )
        people.append(lab)
    doc = _doc(s * seq.frames + f, cam, model, people)
    to_world = np.eye(4)
    to_world[:3, :3], to_world[:3, 3] = cam.R.T, -cam.R.T @ cam.t
    doc["camera"].update(to_world=to_world.tolist(), path=seq.path)
    doc.update(sequence=s, frame=f, frames=seq.frames, fps=seq.fps, time=f / seq.fps)
    return _members(doc, rgb, mask, parts)


def write_fake_sequences(
    out: str | Path,
    sequences: int = 2,
    frames: int = 6,
    fps: float = 30.0,
    people: int = 2,
    *,
    per_shard: int = 1,
    seed: int = 0,
    size: tuple[int, int] = (64, 64),
    exit: bool = True,
    model: blsm.BLSM | None = None,
) -> Path:
    """Write a fake video dataset (``docs/video.md``) of ``sequences`` x ``frames`` samples.

    Every frame is a sample of :func:`make_sample`'s kind (the people drawn as strokes, the dots
    of person 0), with the video labels: ``sequence``, ``frame``, ``frames``, ``fps``, ``time``,
    ``camera.to_world`` and ``camera.path`` (a pan), and per person ``track``, ``velocity_3d`` (the
    model posed at ``t -+ 1 / (2 fps)``), ``contact`` / ``contact_velocity`` (thresholds on the
    region keypoint's height and speed, :data:`synth.sequence.REGION_KEYPOINT`), ``in_view`` (``pixels > 0``)
    and ``motion``; ``blsm.global_orient`` and ``transl`` are world-frame. See
    :class:`_FakeSequence` for the motion; with ``exit`` the last person of every odd sequence
    leaves the image. The manifest is the generator's: ``num_samples = sequences * frames``,
    ``shard_size = per_shard * frames``, ``config.sequence`` = ``enabled``, ``frames``, ``fps``,
    ``per_shard``.

    Returns:
        ``out``.
    """
    model = blsm.load() if model is None else model
    cache: dict[int, _FakeSequence] = {}

    def make(i: int, rng: np.random.Generator) -> dict[str, bytes]:
        s, f = divmod(i, frames)
        if s not in cache:
            cache.clear()
            cache[s] = _FakeSequence(s, seed, model, frames, fps, people, size, exit)
        return make_sequence_frame(s, f, cache[s], rng, model)

    config = {
        "fake": True,
        "image": {"width": size[0], "height": size[1]},
        "sequence": {"enabled": True, "frames": frames, "fps": fps, "per_shard": per_shard},
    }
    writer = ShardWriter(
        out=Path(out), num=sequences * frames, shard_size=per_shard * frames, seed=seed, config=config
    )
    writer.run(make)
    return Path(out)
