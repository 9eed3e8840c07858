"""Temporal metrics of per-frame predictions on sequence datasets (docs/video.md): acceleration error,
acceleration and jitter, as HMMR, VIBE and WHAM report them.

A person's predictions form a *track*, keyed by ``(sequence, track)`` and ordered by frame. Only
*runs* of consecutive frames in which the person was evaluated count: a frame where the person is out
of view (or left out of the evaluation) ends a run, and finite differences never straddle the gap.

Joints are (T, J, 3) in metres, in the camera frame, pelvis-aligned (the pelvis subtracted per frame,
as VIBE's evaluation does before ``compute_error_accel``); a moving camera's own motion is therefore
part of both the predictions' and the labels' accelerations. With ``a[t] = x[t+1] - 2 x[t] + x[t-1]``
and ``j[t] = x[t+2] - 3 x[t+1] + 3 x[t] - x[t-1]``:

- acceleration error: mean over joints and frames of ``|a_pred[t] - a_label[t]|``, mm/frame^2;
- acceleration: mean of ``|a[t]|``, mm/frame^2;
- jitter: mean of ``|j[t]| * fps^3``, km/s^3 (WHAM's released code reports the same quantity in
  units of 10 m/s^3: 1 km/s^3 is 100 of those).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

MIN_ACCEL_FRAMES = 3  # a second difference needs three frames
MIN_JITTER_FRAMES = 4  # a third difference needs four


def _check_joints(name: str, x: torch.Tensor, frames: int) -> None:
    if not isinstance(x, torch.Tensor) or x.ndim != 3 or x.shape[-1] != 3:
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise ValueError(f"{name} must be (T, J, 3) joints over time, got {shape}")
    if x.shape[0] < frames:
        raise ValueError(f"{name} needs at least {frames} frames, got {x.shape[0]}")


def second_difference(x: torch.Tensor) -> torch.Tensor:
    """(T - 2, J, 3) ``x[t+1] - 2 x[t] + x[t-1]`` of (T, J, 3) joints: acceleration per frame^2."""
    _check_joints("x", x, MIN_ACCEL_FRAMES)
    return x[2:] - 2 * x[1:-1] + x[:-2]


def third_difference(x: torch.Tensor) -> torch.Tensor:
    """(T - 3, J, 3) ``x[t+2] - 3 x[t+1] + 3 x[t] - x[t-1]`` of (T, J, 3) joints: jerk per frame^3."""
    _check_joints("x", x, MIN_JITTER_FRAMES)
    return x[3:] - 3 * x[2:-1] + 3 * x[1:-2] - x[:-3]


def accel_error(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(T - 2,) mean over joints of the distance between the accelerations of (T, J, 3) predicted and
    target joints, in the input's unit per frame^2 (VIBE's ``compute_error_accel``). Align both (e.g.
    pelvis at the origin) first."""
    _check_joints("pred", pred, MIN_ACCEL_FRAMES)
    if pred.shape != target.shape:
        raise ValueError(
            f"pred and target must have the same shape, got {tuple(pred.shape)} and {tuple(target.shape)}"
        )
    return (second_difference(pred) - second_difference(target)).norm(dim=-1).mean(-1)


def acceleration(x: torch.Tensor) -> torch.Tensor:
    """(T - 2,) mean over joints of the acceleration's length of (T, J, 3) joints, unit per frame^2."""
    return second_difference(x).norm(dim=-1).mean(-1)


def jitter(x: torch.Tensor, fps: float) -> torch.Tensor:
    """(T - 3,) mean over joints of the jerk's length of (T, J, 3) joints sampled at ``fps`` frames per
    second: ``|third difference| * fps^3``, in the input's unit per s^3 (WHAM's ``compute_jitter``
    before its division by 10)."""
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    return third_difference(x).norm(dim=-1).mean(-1) * float(fps) ** 3


def consecutive_runs(
    sequence: Sequence[int] | np.ndarray, track: Sequence[int] | np.ndarray, frame: Sequence[int] | np.ndarray
) -> list[np.ndarray]:
    """Split items into runs of consecutive frames of one person.

    Args:
        sequence, track, frame: (N,) per item: its sequence id, the person's track in the sequence
            and the frame number.

    Returns:
        One (L,) array of item indices per run, ordered by frame, with frames ``f, f + 1, ..``; runs are
        sorted by (sequence, track, first frame). A missing frame ends a run.

    Raises:
        ValueError: on arrays of different lengths or an item repeated (same sequence, track, frame).
    """
    s, k, f = (np.asarray(a, np.int64).reshape(-1) for a in (sequence, track, frame))
    if not len(s) == len(k) == len(f):
        raise ValueError(
            f"sequence, track and frame must have the same length, got {len(s)}, {len(k)}, {len(f)}"
        )
    if len(s) == 0:
        return []
    order = np.lexsort((f, k, s))
    s, k, f = s[order], k[order], f[order]
    same = (s[1:] == s[:-1]) & (k[1:] == k[:-1])
    if (same & (f[1:] == f[:-1])).any():
        i = int(np.flatnonzero(same & (f[1:] == f[:-1]))[0])
        raise ValueError(f"sequence {s[i]} track {k[i]} frame {f[i]} appears more than once")
    breaks = np.flatnonzero(~(same & (f[1:] == f[:-1] + 1))) + 1
    return np.split(order, breaks)


@dataclasses.dataclass
class TemporalMetrics:
    """Temporal metrics over the runs of a sequence dataset (``None`` where no run is long enough).

    Attributes:
        tracks, runs, frames: people (sequence, track), runs and frames in runs of at least
            :data:`MIN_ACCEL_FRAMES` frames (the acceleration metrics' support).
        jitter_tracks, jitter_runs, jitter_frames: the same for runs of at least :data:`MIN_JITTER_FRAMES`.
        accel_error_mm: mean acceleration error, mm/frame^2.
        accel_mm, label_accel_mm: the predictions' and the labels' mean acceleration, mm/frame^2.
        jitter_km_s3, label_jitter_km_s3: the predictions' and the labels' mean jitter, km/s^3.
        fps: the frame rates of the runs used (sorted, distinct).
    """

    tracks: int = 0
    runs: int = 0
    frames: int = 0
    jitter_tracks: int = 0
    jitter_runs: int = 0
    jitter_frames: int = 0
    accel_error_mm: float | None = None
    accel_mm: float | None = None
    label_accel_mm: float | None = None
    jitter_km_s3: float | None = None
    label_jitter_km_s3: float | None = None
    fps: list[float] = dataclasses.field(default_factory=list)
    note: str = "camera-frame evaluation joints, pelvis-aligned per frame; runs of consecutive in-view frames"

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def temporal_metrics(
    pred: torch.Tensor,
    label: torch.Tensor,
    sequence: Sequence[int] | np.ndarray,
    track: Sequence[int] | np.ndarray,
    frame: Sequence[int] | np.ndarray,
    fps: float | Sequence[float] | np.ndarray,
    pelvis: int = 0,
) -> TemporalMetrics:
    """Acceleration error, acceleration and jitter of per-frame predictions grouped into runs.

    Every frame of every run counts once (a long run weighs more than a short one, as in VIBE, which
    concatenates its sequences' per-frame errors).

    Args:
        pred, label: (N, J, 3) camera-frame joints, metres, one row per evaluated person and frame.
        sequence, track, frame: (N,) the items' sequence, track and frame numbers.
        fps: the frame rate, one for all or (N,) per item (a run takes its first item's).
        pelvis: the pelvis' index among the J joints (subtracted per frame before differencing).

    Returns:
        :class:`TemporalMetrics`; runs shorter than 3 frames (4 for jitter) are left out.
    """
    if (
        not isinstance(pred, torch.Tensor)
        or pred.ndim != 3
        or pred.shape[-1] != 3
        or pred.shape != label.shape
    ):
        shapes = [tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__ for x in (pred, label)]
        raise ValueError(
            f"pred and label must be (N, J, 3) joints of the same shape, got {shapes[0]} and {shapes[1]}"
        )
    n = pred.shape[0]
    rate = np.broadcast_to(np.asarray(fps, np.float64), (n,))
    if n and not (rate > 0).all():
        raise ValueError(f"fps must be positive, got {sorted(set(rate.tolist()))}")
    seq_ids, track_ids = np.asarray(sequence, np.int64).reshape(-1), np.asarray(track, np.int64).reshape(-1)
    if len(seq_ids) != n:
        raise ValueError(
            f"sequence, track and frame must have one entry per row of pred ({n}), got {len(seq_ids)}"
        )
    p = (pred - pred[:, pelvis : pelvis + 1]).double()  # (N, J, 3)
    g = (label - label[:, pelvis : pelvis + 1]).double()
    acc: dict[str, list[torch.Tensor]] = {
        "error": [],
        "pred": [],
        "label": [],
        "jit_pred": [],
        "jit_label": [],
    }
    tracks, jtracks, rates = set(), set(), set()
    out = TemporalMetrics()
    for run in consecutive_runs(seq_ids, track_ids, frame):
        if len(run) < MIN_ACCEL_FRAMES:
            continue
        key = (int(seq_ids[run[0]]), int(track_ids[run[0]]))
        idx = torch.from_numpy(run)
        pr, gr, hz = p[idx], g[idx], float(rate[run[0]])
        tracks.add(key)
        rates.add(hz)
        out.runs += 1
        out.frames += len(run)
        acc["error"].append(accel_error(pr, gr))
        acc["pred"].append(acceleration(pr))
        acc["label"].append(acceleration(gr))
        if len(run) >= MIN_JITTER_FRAMES:
            jtracks.add(key)
            out.jitter_runs += 1
            out.jitter_frames += len(run)
            acc["jit_pred"].append(jitter(pr, hz))
            acc["jit_label"].append(jitter(gr, hz))
    out.tracks, out.jitter_tracks, out.fps = len(tracks), len(jtracks), sorted(rates)

    def mean(name: str, scale: float) -> float | None:
        return float(torch.cat(acc[name]).mean()) * scale if acc[name] else None

    out.accel_error_mm, out.accel_mm, out.label_accel_mm = (
        mean(k, 1000.0) for k in ("error", "pred", "label")
    )
    out.jitter_km_s3, out.label_jitter_km_s3 = (mean(k, 1e-3) for k in ("jit_pred", "jit_label"))
    return out


def sequence_items(ds: Any) -> dict[str, np.ndarray] | None:
    """Per item of a :class:`synth.dataset.images.SynthDataset`: ``sequence``, ``track``, ``frame`` and ``fps``
    from its sample's labels (docs/video.md); None when the dataset holds single images.

    Raises:
        ValueError: naming the sample, when some samples are frames of sequences and others not.
    """
    cols: dict[str, list[Any]] = {"sequence": [], "track": [], "frame": [], "fps": []}
    last, meta, seq = -1, {}, None
    try:
        for s, p in ds.items:  # the people of one image are consecutive: read its labels once
            if s != last:
                last, meta = s, ds.index.json(s)
                has = "sequence" in meta
                if seq is None:
                    seq = has
                elif has != seq:
                    raise ValueError(
                        f"{ds.index.where(s)}.json: {'a' if has else 'no'} sequence frame among "
                        f"{'single images' if has else 'sequence frames'}"
                    )
            if not seq:
                return None
            try:
                cols["sequence"].append(int(meta["sequence"]))
                cols["frame"].append(int(meta["frame"]))
                cols["fps"].append(float(meta["fps"]))
                cols["track"].append(int(meta["people"][p].get("track", p)))
            except (KeyError, IndexError, TypeError, ValueError) as exc:
                raise ValueError(f"{ds.index.where(s)}.json: bad sequence labels ({exc})") from None
    finally:
        ds.index.close()
    if seq is None:
        return None
    return {
        "sequence": np.asarray(cols["sequence"], np.int64),
        "track": np.asarray(cols["track"], np.int64),
        "frame": np.asarray(cols["frame"], np.int64),
        "fps": np.asarray(cols["fps"], np.float64),
    }


def format_temporal(t: dict[str, Any]) -> str:
    """One line of the temporal metrics (``recovery evaluate``'s report)."""
    if not t["runs"]:
        return "  temporal: no run of 3 or more consecutive in-view frames"

    def num(v: float | None, fmt: str) -> str:
        return "n/a" if v is None else format(v, fmt)

    return (
        f"  temporal ({t['tracks']} tracks, {t['runs']} runs, {t['frames']} frames): accel error "
        f"{num(t['accel_error_mm'], '.2f')} mm/frame^2, accel {num(t['accel_mm'], '.2f')} (labels "
        f"{num(t['label_accel_mm'], '.2f')}); jitter {num(t['jitter_km_s3'], '.3g')} km/s^3 (labels "
        f"{num(t['label_jitter_km_s3'], '.3g')}; {t['jitter_frames']} frames)"
    )
