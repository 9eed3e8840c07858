"""The time axis of a sequence fit (thesis Eqs. 6.4-6.5): the frames' times (:func:`frame_times`), the
temporal smoothing S over them (:func:`smoothing`, physical rates, so frames far apart in time are
smoothed less), and the frames whose fit error stands out (:func:`outlier_frames`). Used by
:mod:`blsm.learn.registration.keypoint_fit` and :mod:`blsm.learn.registration.register`."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

__all__ = ["OUTLIER_FACTOR", "OUTLIER_FLOOR", "REFERENCE_FPS", "check_times", "frame_times", "outlier_frames", "smoothing"]

# Frame rate (frames per second) at which the smoothing weights were set (a 15 fps walk,
# docs/markerless.md), and assumed for a sequence whose frame times are unknown: at this spacing S is
# what it was with weights on per-frame differences.
REFERENCE_FPS: float = 15.0

# A frame of a sequence is reported when its keypoint error is over OUTLIER_FACTOR times the median
# of its sequence and over OUTLIER_FLOOR metres (:func:`outlier_frames`).
OUTLIER_FACTOR: float = 2.0
OUTLIER_FLOOR: float = 0.01


def smoothing(joints: torch.Tensor, angles: torch.Tensor, groups: torch.Tensor,
              cfg: Any, times: torch.Tensor | None = None) -> torch.Tensor:
    """S of Eqs. 6.4-6.5: temporal smoothness of consecutive frames of the same group (sequence).

    Physical rates from finite differences over the frames' times: with h1 = t_i - t_{i-1} and
    h2 = t_{i+1} - t_i, the acceleration at frame i is
    ``2 (h1 (J_{i+1} - J_i) - h2 (J_i - J_{i-1})) / (h1 h2 (h1 + h2))`` (``(J_{i+1} - 2 J_i +
    J_{i-1}) / h^2`` for equal spacing) and the velocity between two frames ``(J_i - J_{i-1}) / h``.
    One term per frame triple (pair), as the data term is one per frame: the same motion costs the
    same per frame whether it is sampled at 30 fps or every 4th frame of it, instead of 4^4 = 256
    times more at the wider spacing.

    Args:
        joints: (T, J, 3) posed joints, metres. angles: (T, D) radians.
        groups: (T,) long, the sequence of each frame; differences never straddle two groups.
        cfg: the weights (``smooth_accel``, ``smooth_velocity``, ``smooth_angle_accel`` of a
            :class:`blsm.learn.registration.keypoint_fit.KeypointFitConfig`).
        times: (T,) seconds, increasing within a group (None: frames ``1 / REFERENCE_FPS`` apart).

    Returns:
        () sum over frame triples of ``smooth_accel`` times the mean squared joint acceleration,
        (m/s^2)^2, plus ``smooth_angle_accel`` times the mean squared angular acceleration,
        (rad/s^2)^2, and over frame pairs ``smooth_velocity`` times the mean squared joint velocity,
        (m/s)^2; 0 for fewer than 2 frames.
    """
    out = joints.new_zeros(())
    t_n = joints.shape[0]
    if times is None:
        times = torch.arange(t_n, dtype=joints.dtype) / REFERENCE_FPS
    times = check_times(times, t_n).to(joints.dtype)
    same2 = groups[1:] == groups[:-1]
    h = times[1:] - times[:-1]  # (T-1,) seconds
    if bool((h[same2] <= 0).any()):
        i = int((same2 & (h <= 0)).nonzero()[0])
        raise ValueError(f"frame times must increase within a sequence: frame {i + 1} at "
                         f"{float(times[i + 1]):.4g} s follows {float(times[i]):.4g} s")
    h = torch.where(same2, h, torch.ones_like(h))  # no difference straddles two groups
    if t_n >= 2 and cfg.smooth_velocity > 0:
        vel = ((joints[1:] - joints[:-1]) / h[:, None, None]).square().sum(-1).mean(-1)
        out = out + cfg.smooth_velocity * (vel * same2.to(joints.dtype)).sum()
    if t_n >= 3:
        same = (same2[1:] & same2[:-1]).to(joints.dtype)
        h1, h2 = h[:-1], h[1:]  # (T-2,)

        def accel(x: torch.Tensor) -> torch.Tensor:
            s = [-1] + [1] * (x.dim() - 1)
            a, b = h1.reshape(s), h2.reshape(s)
            return 2 * (a * (x[2:] - x[1:-1]) - b * (x[1:-1] - x[:-2])) / (a * b * (a + b))

        acc = accel(joints).square().sum(-1).mean(-1)
        aacc = accel(angles).square().mean(-1)
        out = out + ((cfg.smooth_accel * acc + cfg.smooth_angle_accel * aacc) * same).sum()
    return out


def check_times(times: torch.Tensor | None, t_n: int) -> torch.Tensor | None:
    """``times`` unchanged if it is None or (T,) = (``t_n``,), else a ValueError naming both shapes."""
    if times is not None and tuple(times.shape) != (t_n,):
        raise ValueError(f"times must be (T,) = ({t_n},), got {tuple(times.shape)}")
    return times


def frame_times(metas: Sequence[dict | None], fps: float = 0.0) -> tuple[torch.Tensor | None, str]:
    """The times of a sequence's frames for :func:`smoothing`, and where they came from.

    In this order: ``fps`` > 0 (``KeypointFitConfig.fps``, ``blsm register --fps``): frame t at
    ``t / fps``; every scan's ``meta["time"]`` (seconds, as :func:`blsm.learn.markerless.sequence_scans.make_sequence`
    writes); every scan's ``meta["pose"]`` (the frame's index in its sequence) over ``meta["fps"]``
    (the sequence's frame rate), both written by ``make_sequence`` before ``time`` was; else None
    (``smoothing`` then takes the frames ``1 / REFERENCE_FPS`` apart, the behaviour before frame times).

    Args:
        metas: the scans' ``meta`` dicts (None: no meta), in frame order.
        fps: frames per second of the frames as given, 0: unknown.

    Returns:
        ((T,) float64 seconds or None, a short phrase naming the source).
    """
    if fps > 0:
        return torch.arange(len(metas), dtype=torch.float64) / fps, f"--fps / fps setting {fps:g}"
    metas = [m or {} for m in metas]

    def number(m: dict, key: str) -> float | None:
        v = m.get(key)
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and bool(np.isfinite(v))
        return float(v) if ok else None

    times = [number(m, "time") for m in metas]
    if metas and all(t is not None for t in times):
        return torch.tensor(times, dtype=torch.float64), "the scans' meta time"
    rates, index = [number(m, "fps") for m in metas], [number(m, "pose") for m in metas]
    one_rate = all(r is not None and r > 0 for r in rates) and len(set(rates)) == 1
    if metas and one_rate and all(i is not None for i in index):
        t = torch.tensor(index, dtype=torch.float64) / rates[0]
        return t, f"the scans' meta frame index (pose) and fps {rates[0]:g}"
    return None, f"unknown, {REFERENCE_FPS:g} fps assumed (set --fps)"


def outlier_frames(errors: torch.Tensor, groups: torch.Tensor, factor: float = OUTLIER_FACTOR,
                   floor: float = OUTLIER_FLOOR) -> list[int]:
    """Frames whose keypoint error is far above the rest of their sequence.

    "Far above": over ``factor`` (2) times the median error of the frame's group and over ``floor``
    (0.01 m, so that a sequence fitted to a few millimetres does not report 5 mm frames; the
    over-smoothed frame of issue 53's reproduction had 13.9 mm against a median of 6.8 mm). Groups of
    fewer than 3 frames report none (with 2 frames neither is above twice their median).

    Args:
        errors: (T,) per-frame keypoint errors, metres (``KeypointFit.keypoint_error``).
        groups: (T,) long, the sequence of each frame.

    Returns:
        The indices of the outlying frames, increasing.
    """
    out = []
    for g in groups.unique():
        idx = (groups == g).nonzero()[:, 0]
        if len(idx) < 3:
            continue
        e = errors[idx].double()
        bad = (e > factor * e.median()) & (e > floor)
        out += idx[bad].tolist()
    return sorted(out)
