"""``synth validate`` for sequences (docs/video.md): continuity through a clip and contact against geometry.

Per frame (on the mesh :mod:`synth.validate` rebuilds from the frame's parameters):

- ``camera.to_world`` is the inverse of ``[R | t]``;
- no vertex of a body is further below the ground ``y = 0`` than a moving foot may dip
  (``GROUND_TOLERANCE_M``, :mod:`synth.sequence`, Grounding);
- where ``contact`` says a region touches the ground, one of the region's vertices is within
  ``contact_rule.distance`` of it (the speed half of the rule needs the neighbouring half-frames,
  which the labels do not hold).

Per sequence (its frames in one shard, in order):

- the frames are ``0 .. T-1`` under keys ``s T + f``, with ``time = f / fps``;
- every frame lists the same people (subjects) in the same order, ``track`` = their index;
- no jump: between two frames a person's root moves at most ``MAX_PERSON_SPEED`` m/s, the camera's
  centre at most ``MAX_CAMERA_SPEED`` m/s and turns at most ``MAX_CAMERA_TURN`` degrees a second;
- ``velocity_3d`` agrees with the stored keypoints' own central difference over the neighbouring
  frames to ``VELOCITY_TOLERANCE`` m/s plus half that difference's speed: the labels' half-frame
  difference and the frames' differ where the motion changes within a frame (a hand turning at
  5 m/s), so this catches gross errors only (a wrong unit, sign, order or frame).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

GROUND_TOLERANCE_M = 0.021
"""Metres: :data:`synth.sequence.PENETRATION_M` (a moving foot may dip that far) and 1 mm."""
MAX_PERSON_SPEED = 8.0
MAX_CAMERA_SPEED = 10.0
MAX_CAMERA_TURN = 180.0
VELOCITY_TOLERANCE = 1.0


def check_contact(
    model: Any,
    bones: np.ndarray,
    verts: np.ndarray,
    keypoints: np.ndarray,
    person: dict[str, Any],
    doc: dict[str, Any],
) -> list[str]:
    """What is wrong with one person's ground and ``contact`` labels on its rebuilt body ``verts``."""
    from synth.sequence import contact_regions

    out = []
    low = float(verts[:, 1].min())
    if low < -GROUND_TOLERANCE_M:
        out.append(f"the body is {-low * 1000:.1f} mm below the ground")
    rule = doc.get("contact_rule") or {}
    dist = float(rule.get("distance", 0.0))
    regions = contact_regions(model, bones, verts, keypoints)
    for name, touching in person["contact"].items():
        if name not in regions:
            out.append(f"contact names an unknown region {name!r}")
            continue
        idx = regions[name]
        if touching and (len(idx) == 0 or float(verts[idx, 1].min()) > dist + 1e-6):
            h = float(verts[idx, 1].min()) if len(idx) else math.inf
            out.append(
                f"contact {name}: the region is {h * 1000:.1f} mm above the ground, over {dist * 1000:.0f} mm"
            )
    c = np.asarray(doc["camera"].get("to_world", np.eye(4)), np.float64)
    r, t = np.asarray(doc["camera"]["R"], np.float64), np.asarray(doc["camera"]["t"], np.float64)
    if np.abs(c[:3, :3] @ r - np.eye(3)).max() > 1e-5 or np.abs(c[:3, 3] + r.T @ t).max() > 1e-5:
        out.append("camera.to_world is not the inverse of [R | t]")
    return out


def check_sequences(docs: dict[str, dict[str, Any] | None], cfg: dict[str, Any], first: int) -> list[str]:
    """What is wrong with the sequences of one shard (``docs``: key -> labels, in key order)."""
    T, fps = int(cfg["frames"]), float(cfg["fps"])
    out: list[str] = []
    keys = sorted(docs)
    if any(docs[k] is None for k in keys):
        return []  # the sample's own failure is reported already
    if len(keys) % T:
        return [f"holds {len(keys)} frames, not whole sequences of {T}"]
    for a in range(0, len(keys), T):
        clip = [docs[k] for k in keys[a : a + T]]  # type: ignore[misc]
        seq = clip[0]["sequence"]
        where = f"sequence {seq}"
        if [int(k) for k in keys[a : a + T]] != [seq * T + f for f in range(T)]:
            out.append(f"{where}: keys are not s*T + f in order")
        for f, d in enumerate(clip):
            if d["sequence"] != seq or d["frame"] != f or abs(d["time"] - f / fps) > 1e-6:
                out.append(
                    f"{where}: frame {f} is labelled sequence {d['sequence']} frame {d['frame']} time {d['time']}"
                )
        out += _continuity(where, clip, fps)
    return out


def _continuity(where: str, clip: list[dict[str, Any]], fps: float) -> list[str]:
    out: list[str] = []
    subjects = [p["subject"] for p in clip[0]["people"]]
    for d in clip:
        if [p["subject"] for p in d["people"]] != subjects or [p["track"] for p in d["people"]] != list(
            range(len(subjects))
        ):
            return [f"{where}: frame {d['frame']} lists other people or tracks than frame 0"]
    eyes = np.array([-np.asarray(d["camera"]["R"]).T @ np.asarray(d["camera"]["t"]) for d in clip])
    rots = np.array([d["camera"]["R"] for d in clip], np.float64)
    step = np.linalg.norm(np.diff(eyes, axis=0), axis=1) * fps
    if (step > MAX_CAMERA_SPEED).any():
        f = int(step.argmax())
        out.append(f"{where}: the camera jumps {step[f] / fps:.3f} m between frames {f} and {f + 1}")
    cos = np.clip((np.einsum("tij,tij->t", rots[1:], rots[:-1]) - 1) / 2, -1, 1)
    turn = np.degrees(np.arccos(cos)) * fps
    if (turn > MAX_CAMERA_TURN).any():
        f = int(turn.argmax())
        out.append(f"{where}: the camera turns {turn[f] / fps:.2f} degrees between frames {f} and {f + 1}")
    for i in range(len(subjects)):
        root = np.array([d["people"][i]["blsm"]["transl"] for d in clip], np.float64)
        speed = np.linalg.norm(np.diff(root, axis=0), axis=1) * fps
        if (speed > MAX_PERSON_SPEED).any():
            f = int(speed.argmax())
            out.append(f"{where}: person {i} jumps {speed[f] / fps:.3f} m between frames {f} and {f + 1}")
        kp = np.array([d["people"][i]["keypoints_3d"] for d in clip], np.float64)
        vel = np.array([d["people"][i]["velocity_3d"] for d in clip], np.float64)
        if len(clip) >= 3:
            diff = (kp[2:] - kp[:-2]) * fps / 2
            err = np.linalg.norm(diff - vel[1:-1], axis=-1)
            allowed = VELOCITY_TOLERANCE + 0.5 * np.linalg.norm(diff, axis=-1)
            if (err > allowed).any():
                f = int((err - allowed).max(1).argmax()) + 1
                out.append(
                    f"{where}: person {i} velocity_3d differs from the keypoints' motion by {err.max():.2f} m/s at frame {f}"
                )
    return out
