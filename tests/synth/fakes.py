"""A small fake dataset in the sample format of :mod:`synth.format`, made without Mitsuba.

Each sample holds one or two BLSM people posed at random and seen by an OpenCV camera whose
principal point is off centre. The labels follow the format exactly: keypoints are the model's,
projected with :meth:`blsm.camera.Camera.project`; the parts map is thick strokes along the bones
(one label per bone's part, left/right the person's own), the mask is where a person's strokes are
(person 0 in front); the image is the dimmed part colours on grey with a ``DOT`` x ``DOT`` square of
colour :func:`dot_colour` ``(k)`` centred on the pixel of every in-frame keypoint ``k`` of person 0.

Sample 1 has a second person far out of frame (no pixels, ``box`` None), samples 3, 5, ... one
person, the others two.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

import blsm
from blsm import skeleton
from blsm.camera import Camera, look_at_camera
from synth import format as fmt
from synth.shards import ShardWriter

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


def make_sample(
    index: int, rng: np.random.Generator, model: blsm.BLSM, size: tuple[int, int]
) -> dict[str, bytes]:
    """All members of fake sample ``index`` (``size`` is (width, height))."""
    w, h = size
    names = model.keypoint_names
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
    with torch.no_grad():
        out = model(
            **{k: torch.tensor(np.stack([q[k] for q in params]), dtype=torch.float32) for k in params[0]}
        )
    kps = out.keypoints.double().numpy()
    pelvis = kps[0, 0]
    eye = pelvis + [rng.uniform(-0.5, 0.5), 0.3, 3.0]
    cam = look_at_camera(eye, pelvis, up=(0.1, 1.0, 0.0), fov_y_deg=50, width=w, height=h)
    kmat = cam.K.copy()
    kmat[0, 2] += 7.3
    kmat[1, 2] -= 4.1
    cam = Camera(K=kmat, R=cam.R, t=cam.t, width=w, height=h)

    mask = np.zeros((h, w), np.uint8)
    parts = np.zeros((h, w), np.uint8)
    uvs = [cam.project(kp) for kp in kps]
    for p in reversed(range(n_people)):  # person 0 last: in front
        layer = Image.new("L", (w, h), 0)
        draw = ImageDraw.Draw(layer)
        for a, b, label in _strokes(model):
            ua, ub = uvs[p][names.index(a)], uvs[p][names.index(b)]
            draw.line([tuple(ua - 0.5), tuple(ub - 0.5)], fill=label, width=9)  # PIL: centres at integers
        lab = np.asarray(layer)
        parts = np.where(lab > 0, lab, parts)
        mask = np.where(lab > 0, p + 1, mask).astype(np.uint8)
    rgb = np.where(parts[..., None] > 0, fmt.PART_PALETTE[parts] // 2, BACKGROUND).astype(np.uint8)
    r = DOT // 2
    for k, (u, v) in enumerate(np.floor(uvs[0]).astype(int)):
        if 0 <= u < w and 0 <= v < h:
            rgb[max(v - r, 0) : v + r + 1, max(u - r, 0) : u + r + 1] = dot_colour(k)

    people = []
    for p, q in enumerate(params):
        uv, kc = uvs[p], cam.world_to_camera(kps[p])
        px = np.floor(uv).astype(int)
        in_frame = (kc[:, 2] > 0) & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
        visible = in_frame.copy()
        for k in np.flatnonzero(in_frame):
            visible[k] = mask[px[k, 1], px[k, 0]] == p + 1 and rng.uniform() > 0.1
        ys, xs = np.nonzero(mask == p + 1)
        box = [int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1] if len(xs) else None
        people.append(
            {
                "subject": f"fake{p}",
                "pipeline": "blsm",
                "motion": {"source": "random", "clip": None, "frame": 0},
                "blsm": {
                    "pose": q["pose"].tolist(),
                    "angles": out.angles[p].double().tolist(),
                    "bone": q["bone"].tolist(),
                    "shape": q["shape"].tolist(),
                    "global_orient": q["global_orient"].tolist(),
                    "transl": q["transl"].tolist(),
                },
                "bone_lengths": [0.1] * len(skeleton.BONE_NAMES),
                "keypoints_3d": kps[p].tolist(),
                "keypoints_3d_cam": kc.tolist(),
                "keypoints_2d": uv.tolist(),
                "visible": visible.tolist(),
                "in_frame": in_frame.tolist(),
                "box": box,
                "box_full": [*(uv.min(0) - 5).tolist(), *(uv.max(0) + 5).tolist()],
                "pixels": int(len(xs)),
            }
        )
    doc = {
        "format": fmt.FORMAT,
        "version": fmt.VERSION,
        "index": index,
        "seed": 0,
        "image": {"width": w, "height": h, "pixel_center": 0.5},
        "camera": {"K": cam.K.tolist(), "R": cam.R.tolist(), "t": cam.t.tolist(), "info": {"fake": True}},
        "background": {"kind": "flat", "value": BACKGROUND},
        "keypoint_names": list(names),
        "bone_names": list(model.bone_names),
        "part_names": list(model.part_names),
        "people": people,
    }
    return {
        "rgb.png": fmt.encode_png(rgb),
        "json": fmt.encode_json(doc),
        "mask.png": fmt.encode_png(mask),
        "parts.png": fmt.encode_png(parts, fmt.PART_PALETTE),
        "bones.png": fmt.encode_png(np.zeros((h, w), np.uint8), fmt.BONE_PALETTE),
        "depth.exr": fmt.encode_exr(np.zeros((h, w), np.float32)),
        "corr.npy.gz": fmt.encode_npy_gz(np.full((h, w, 3), -1.0, np.float32)),
    }


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
