"""``synth validate`` for sequences (docs/video.md): continuity through a clip and contact against geometry.

Per frame (on the mesh :mod:`synth.validate` rebuilds from the frame's parameters):

- ``camera.to_world`` is the inverse of ``[R | t]``;
- no vertex of a body is further below the ground ``y = 0`` than a moving foot may dip
  (``GROUND_TOLERANCE_M``, :mod:`synth.sequence`, Grounding);
- where ``contact`` says a region touches the ground, one of the region's vertices is within
  ``contact_rule.distance`` of it (the regions are the person's at frame 0, as the generator fixes them).

Per sequence (its frames in one shard, in order):

- the frames are ``0 .. T-1`` under keys ``s T + f``, with ``time = f / fps``;
- every frame lists the same people (subjects) in the same order, ``track`` = their index;
- no jump: between two frames a person's root moves at most ``MAX_PERSON_SPEED`` m/s, the camera's
  centre at most ``MAX_CAMERA_SPEED`` m/s and turns at most ``MAX_CAMERA_TURN`` degrees a second;
- ``contact`` is the whole rule at every frame but the first and last: a region touches the ground
  exactly when one of its vertices is within ``distance`` of it and slower than ``speed``, the
  speed the central difference of the rebuilt bodies of the neighbouring frames (a vertex within
  rounding of a threshold decides nothing);
- ``velocity_3d`` is the stored keypoints' own central difference over the neighbouring frames, to
  ``VELOCITY_TOLERANCE`` m/s (the labels' 6-decimal rounding of the keypoints, times the frame rate).
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
VELOCITY_TOLERANCE = 1e-3


def check_contact(
    model: Any,
    bones: np.ndarray,
    verts: np.ndarray,
    keypoints: np.ndarray,
    person: dict[str, Any],
    doc: dict[str, Any],
    regions_of: dict[tuple, dict[str, np.ndarray]] | None = None,
) -> list[str]:
    """What is wrong with one person's ground and ``contact`` labels on its rebuilt body ``verts``.
    ``regions_of`` caches each person's regions by ``(sequence, track)`` from its first frame seen
    (frame 0 when it decodes); the region vertices are kept in ``person["_region_vertices"]`` for
    :func:`check_sequences`."""
    from synth.sequence import contact_regions

    out = []
    key = (doc.get("sequence"), person.get("track"))
    if regions_of is None:
        regions_of = {}
    if key not in regions_of:
        regions_of[key] = contact_regions(model, bones, verts, keypoints)
    regions = regions_of[key]
    person["_region_vertices"] = {r: verts[idx] for r, idx in regions.items()}
    low = float(verts[:, 1].min())
    if low < -GROUND_TOLERANCE_M:
        out.append(f"the body is {-low * 1000:.1f} mm below the ground")
    rule = doc.get("contact_rule") or {}
    dist = float(rule.get("distance", 0.0))
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
        out += _contact_speed(where, clip, fps)
    return out


def _contact_speed(where: str, clip: list[dict[str, Any]], fps: float) -> list[str]:
    """The whole contact rule at the inner frames, on the rebuilt region vertices."""
    out: list[str] = []
    rule = clip[0].get("contact_rule") or {}
    if not rule or any("_region_vertices" not in p for d in clip for p in d["people"]):
        return out
    dist, speed = float(rule["distance"]), float(rule["speed"])
    for i in range(len(clip[0]["people"])):
        for f in range(1, len(clip) - 1):
            p = clip[f]["people"][i]
            for r, told in p["contact"].items():
                v0, v, v1 = (clip[g]["people"][i]["_region_vertices"][r] for g in (f - 1, f, f + 1))
                if len(v) == 0:
                    continue
                h, s = v[:, 1], np.linalg.norm(v1 - v0, axis=1) * fps / 2
                sure = (np.abs(h - dist) > 1e-4) & (np.abs(s - speed) > 1e-3)
                touching = (h <= dist) & (s <= speed)
                if bool(touching[sure].any()) != told and (sure | ~touching).all():
                    out.append(f"{where}: person {i} frame {f} contact {r} is {told}, the rebuilt bodies say {not told}")
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
            allowed = VELOCITY_TOLERANCE + 2e-6 * fps  # rounding of the keypoints and the labels
            if (err > allowed).any():
                f = int((err - allowed).max(1).argmax()) + 1
                out.append(
                    f"{where}: person {i} velocity_3d differs from the keypoints' motion by {err.max():.2f} m/s at frame {f}"
                )
    return out
