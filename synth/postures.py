"""Postures beyond the pose prior: people seated on a seat, and arms anywhere in their range.

The packaged pose prior (:mod:`blsm.mocap.prior`) is learnt from the CMU clips of the motion
library: walking, running, jumping, dancing, playground play. It holds almost no seated person and
few arms held in front of the body, while photographs of people are full of both (musicians,
people at tables, audiences). Two options of ``poses`` widen it (both 0, off, by default), each
applied to a prior draw before the plausibility check (:mod:`blsm.mocap.plausible`), so that a
posture whose limb passes through the torso is re-drawn like any prior pose:

- ``seated_rate``: the probability that a person sits (:func:`seated_angles`): both hips flexed
  around one draw of 65-105 degrees (each side within 10 of it), the knees bent so that the shins
  hang within about 25 degrees of vertical (knee flex = hip flex - 10 + U(-25, 15) degrees; the
  10 degrees of Anny's bent rest knee taken out), hips abducted -5 to 25 degrees and rotated within
  15, ankles -10 to 25; trunk, head and arms stay the prior's. A box seat is put under the
  thighs (:func:`seat_under`), so the person sits on something; it is one of the sample's
  ``occluders`` (its pixels belong to no person, the keypoints it hides are not visible).
- ``arms_rate``: the probability that each arm's nine atoms (clavicle, shoulder, elbow, wrist) are
  drawn uniformly within their joint limits (``blsm/data/dofs.yaml``) instead of the prior's:
  arms raised, held forward, folded, on the hips, as photographs show them. Uniform within the
  limits is not a prior of real arms; the plausibility check removes the arms through the torso.

The label's ``motion`` records ``posture`` (``seated``) and ``arms`` (the arms drawn uniformly:
``left``, ``right``) for the people these options changed.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from blsm.joint_limits import angles_from_unconstrained, unconstrained_from_angles
from synth.occluders import Occluder, draw_colour

ARM_JOINTS = ("clavicle", "shoulder", "elbow", "wrist")
SEAT_WIDTH_MARGIN = (0.08, 0.2)  # metres beyond the hips on each side
SEAT_MIN_HEIGHT = 0.2  # a seat lower than this (metres) means the thighs did not come forward: no seat


def seated_angles(theta: np.ndarray, names: list[str], limits: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``theta`` (D,) radians with the legs seated (the module docstring's ranges), clipped to
    ``limits`` (D, 2); ``names`` the atoms' names (``hip_l.flex``, ...)."""
    out = np.array(theta, np.float64)
    deg = math.radians
    hip = rng.uniform(65.0, 105.0)
    for side in ("l", "r"):
        h = hip + rng.uniform(-10.0, 10.0)
        values = {
            f"hip_{side}.flex": h, f"hip_{side}.abduct": rng.uniform(-5.0, 25.0),
            f"hip_{side}.rotate": rng.uniform(-15.0, 15.0), f"knee_{side}.flex": h - 10.0 + rng.uniform(-25.0, 15.0),
            f"ankle_{side}.plantarflex": rng.uniform(-10.0, 25.0),
        }  # fmt: skip
        for name, v in values.items():
            out[names.index(name)] = deg(v)
    return np.clip(out, limits[:, 0], limits[:, 1])


def uniform_arm(theta: np.ndarray, names: list[str], limits: np.ndarray, side: str, rng: np.random.Generator) -> np.ndarray:
    """``theta`` (D,) with arm ``side``'s atoms (``l`` or ``r``) uniform within ``limits``."""
    out = np.array(theta, np.float64)
    for i, n in enumerate(names):
        joint = n.split(".")[0]
        if joint.endswith(f"_{side}") and joint[:-2] in ARM_JOINTS:
            out[i] = rng.uniform(limits[i, 0], limits[i, 1])
    return out


def vary(x: np.ndarray, model, seated_rate: float, arms_rate: float, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """A prior draw ``x`` (47,) with the postures of the module docstring applied; returns the new
    unconstrained values and the ``motion`` entries that say what changed (empty: nothing)."""
    limits_t = model.dof_table.limits_tensor()
    limits = limits_t.numpy()
    names = model.dof_names
    theta = angles_from_unconstrained(torch.from_numpy(np.asarray(x, np.float64))[None], limits_t)[0].numpy()
    info: dict = {}
    # Draw every number whether or not it is used, so one option does not shift the other's stream.
    sit, arm_u = rng.uniform(), rng.uniform(size=2)
    legs = seated_angles(theta, names, limits, rng)
    if sit < seated_rate:
        theta, info["posture"] = legs, "seated"
    arms = []
    for side, u in zip(("l", "r"), arm_u):
        drawn = uniform_arm(theta, names, limits, side, rng)
        if u < arms_rate:
            theta = drawn
            arms.append("left" if side == "l" else "right")
    if arms:
        info["arms"] = arms
    if not info:
        return np.asarray(x, np.float32), info
    return unconstrained_from_angles(torch.from_numpy(theta)[None], limits_t)[0].numpy().astype(np.float32), info


def seat_under(shell: np.ndarray, joints: np.ndarray, bone_names: list[str], rng: np.random.Generator) -> Occluder | None:
    """A box seat under a seated person placed on the ground (``shell`` (N, 3) the vertices of body,
    hair and clothes; ``joints`` (J, 3) in ``bone_names`` order), or None where the thighs do not
    come forward enough to sit on (its top below :data:`SEAT_MIN_HEIGHT`).

    The seat's frame follows the pelvis: x from the right hip to the left, z forward (the thighs'
    direction). It spans the hips plus 8-20 cm on each side (never wider than the person's own
    sideways extent, so it stays inside their footprint and clear of other people); front to back,
    from the back of the buttocks (the shell's rearmost vertex below the hips) to 10 cm short of the
    nearer knee and behind the shins and feet (every vertex below 0.6 times the knees' height); its
    top is the lowest vertex of body, hair or clothes above that footprint, so the person rests on it.
    """
    hip_l, hip_r = joints[bone_names.index("hip_l")], joints[bone_names.index("hip_r")]
    knee_l, knee_r = joints[bone_names.index("knee_l")], joints[bone_names.index("knee_r")]
    ax = (hip_l - hip_r)[[0, 2]]
    ax = ax / max(float(np.linalg.norm(ax)), 1e-9)
    fwd = np.array([-ax[1], ax[0]])  # x cross y -> z in the ground plane: (x, z) -> (-z, x) turned
    if fwd @ (0.5 * (knee_l + knee_r) - 0.5 * (hip_l + hip_r))[[0, 2]] < 0:
        fwd = -fwd
    centre_hips = 0.5 * (hip_l + hip_r)[[0, 2]]
    rel = shell[:, [0, 2]] - centre_hips
    u, w = rel @ ax, rel @ fwd  # sideways, forward
    half = 0.5 * float(np.linalg.norm((hip_l - hip_r)[[0, 2]])) + rng.uniform(*SEAT_WIDTH_MARGIN)
    half = min(half, float(np.abs(u).max()))  # never wider than the person: it stays in their footprint
    within = np.abs(u) <= half
    front = min(float((knee_l[[0, 2]] - centre_hips) @ fwd), float((knee_r[[0, 2]] - centre_hips) @ fwd)) - 0.10
    pelvis_y = 0.5 * (hip_l[1] + hip_r[1])
    knee_y = 0.5 * (knee_l[1] + knee_r[1])
    shins = within & (shell[:, 1] < 0.6 * knee_y)  # shins and feet: the seat stays behind them
    if shins.any():
        front = min(front, float(w[shins].min()) - 0.02)
    low = within & (shell[:, 1] < pelvis_y)  # the buttocks' and thighs' underside, not the back
    back = float(w[low].min()) if low.any() else -0.15
    if front - back < 0.15:
        return None
    over = within & (w >= back) & (w <= front)
    if not over.any():
        return None
    top = float(shell[over, 1].min())
    if top < SEAT_MIN_HEIGHT:
        return None
    mid = centre_hips + fwd * (0.5 * (back + front))
    yaw = math.atan2(-ax[1], ax[0])  # the box's width axis (its x) along ax
    colour = tuple(float(c) for c in draw_colour(rng))
    return Occluder("box", (float(mid[0]), float(mid[1])), (2.0 * half, top, front - back), yaw, colour, int(rng.integers(2**31)))


def seats(people: list, bone_names: list[str], rng: np.random.Generator) -> list[Occluder]:
    """A seat under each placed person whose ``motion`` says ``posture: seated`` (:func:`seat_under`);
    each such person's ``motion["seat"]`` records whether one was put (False: no room under the
    thighs; the person is rendered crouching, labels as ever)."""
    out = []
    for p in people:
        if p.motion.get("posture") != "seated":
            continue
        s = seat_under(p.shell(), p.joints, bone_names, rng)
        p.motion["seat"] = s is not None
        if s is not None:
            out.append(s)
    return out
