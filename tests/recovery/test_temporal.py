"""recovery.eval.temporal: acceleration error, acceleration and jitter over runs of consecutive frames, and
the ``temporal`` section ``recovery evaluate`` writes for a sequence dataset."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from recovery_helpers import one_thread

from recovery.eval.temporal import (
    accel_error,
    acceleration,
    consecutive_runs,
    format_temporal,
    jitter,
    second_difference,
    temporal_metrics,
    third_difference,
)


def _track(t: int, j: int = 5, velocity: float = 0.01, accel: float = 0.0, jerk: float = 0.0, seed: int = 0):
    """(T, J, 3) joints: a random skeleton moving along (1, 2, 2) / 3 with position
    ``v t + a t^2 / 2 + c t^3`` per frame (metres, t in frames)."""
    gen = torch.Generator().manual_seed(seed)
    base = torch.randn(j, 3, generator=gen, dtype=torch.float64)
    d = torch.tensor([1.0, 2.0, 2.0], dtype=torch.float64) / 3
    tt = torch.arange(t, dtype=torch.float64)
    s = velocity * tt + accel * tt**2 / 2 + jerk * tt**3
    return base + s[:, None, None] * d


def _with_pelvis(x: torch.Tensor) -> torch.Tensor:
    """(T, 1 + J, 3): a still pelvis at the origin as joint 0, then ``x``."""
    return torch.cat([torch.zeros_like(x[:, :1]), x], 1)


def _vibe_accel_error(gt: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """VIBE's ``compute_error_accel`` (without its visibility mask), written out joint by joint."""
    out = []
    for t in range(1, len(gt) - 1):
        errs = []
        for k in range(gt.shape[1]):
            ag = gt[t - 1, k] - 2 * gt[t, k] + gt[t + 1, k]
            ap = pred[t - 1, k] - 2 * pred[t, k] + pred[t + 1, k]
            errs.append(math.dist(ap, ag))
        out.append(sum(errs) / len(errs))
    return np.asarray(out)


def test_constant_velocity_has_no_acceleration_or_jitter():
    x = _track(8, velocity=0.05)
    assert second_difference(x).shape == (6, 5, 3) and third_difference(x).shape == (5, 5, 3)
    assert acceleration(x).abs().max() < 1e-12
    assert jitter(x, 30.0).abs().max() < 1e-6
    assert (
        accel_error(x, _track(8, velocity=-0.3, seed=1)).abs().max() < 1e-12
    )  # velocities differ: no matter


def test_quadratic_motion_has_its_known_acceleration():
    a = 0.002  # m/frame^2
    x = _track(7, accel=a)
    assert acceleration(x) == pytest.approx(torch.full((5,), a, dtype=torch.float64), abs=1e-12)
    assert accel_error(x, _track(7)) == pytest.approx(torch.full((5,), a, dtype=torch.float64), abs=1e-12)
    assert jitter(x, 30.0).abs().max() < 1e-6  # a constant acceleration has no jerk


def test_cubic_motion_has_its_known_jitter():
    c = 1e-3  # m/frame^3: third difference 6 c per frame^3, times fps^3 per s^3
    x = _track(9, jerk=c)
    expect = 6 * c * 30.0**3  # 162 m/s^3
    assert jitter(x, 30.0) == pytest.approx(torch.full((6,), expect, dtype=torch.float64), rel=1e-9)
    assert jitter(x, 60.0) == pytest.approx(jitter(x, 30.0) * 8, rel=1e-12)


def test_noise_raises_jitter_and_acceleration():
    gen = torch.Generator().manual_seed(3)
    x = _track(20, velocity=0.02, accel=0.001)
    noisy = x + 0.005 * torch.randn(x.shape, generator=gen, dtype=torch.float64)
    assert jitter(noisy, 30.0).mean() > 100 * (jitter(x, 30.0).mean() + 1.0)
    assert acceleration(noisy).mean() > 2 * acceleration(x).mean()
    assert accel_error(noisy, x).mean() > 0.005


def test_accel_error_matches_vibe_loop():
    gen = torch.Generator().manual_seed(4)
    gt = torch.randn(10, 6, 3, generator=gen, dtype=torch.float64)
    pred = gt + 0.1 * torch.randn(10, 6, 3, generator=gen, dtype=torch.float64)
    np.testing.assert_allclose(
        accel_error(pred, gt).numpy(), _vibe_accel_error(gt.numpy(), pred.numpy()), rtol=1e-12
    )


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: acceleration(torch.zeros(2, 5, 3)), "at least 3 frames"),
        (lambda: jitter(torch.zeros(3, 5, 3), 30.0), "at least 4 frames"),
        (lambda: jitter(torch.zeros(5, 5, 3), 0.0), "fps must be positive"),
        (lambda: acceleration(torch.zeros(5, 3)), r"\(T, J, 3\)"),
        (lambda: accel_error(torch.zeros(5, 4, 3), torch.zeros(5, 3, 3)), "same shape"),
        (lambda: consecutive_runs([0, 0], [0, 0], [1, 1]), "frame 1 appears more than once"),
        (lambda: consecutive_runs([0, 0], [0], [1, 2]), "same length"),
        (
            lambda: temporal_metrics(
                torch.zeros(3, 2, 3), torch.zeros(3, 2, 3), [0] * 2, [0] * 2, [0, 1], 30.0
            ),
            "one entry",
        ),
        (
            lambda: temporal_metrics(
                torch.zeros(3, 2, 3), torch.zeros(3, 3, 3), [0] * 3, [0] * 3, [0, 1, 2], 30.0
            ),
            "same shape",
        ),
    ],
)
def test_bad_input(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_consecutive_runs_split_at_gaps_and_by_person():
    # items in any order: (sequence, track, frame)
    items = [
        (1, 0, 3),
        (0, 1, 0),
        (0, 0, 2),
        (0, 0, 0),
        (0, 0, 1),
        (0, 0, 4),
        (0, 1, 1),
        (1, 0, 2),
        (0, 0, 5),
    ]
    s, k, f = (np.array(c) for c in zip(*items, strict=True))
    runs = consecutive_runs(s, k, f)
    got = [[items[i] for i in r] for r in runs]
    assert got == [
        [(0, 0, 0), (0, 0, 1), (0, 0, 2)],  # frame 3 missing: a new run starts at 4
        [(0, 0, 4), (0, 0, 5)],
        [(0, 1, 0), (0, 1, 1)],
        [(1, 0, 2), (1, 0, 3)],
    ]
    assert consecutive_runs([], [], []) == []


def test_temporal_metrics_over_runs():
    """Two people in one sequence and one in another; per-frame rows shuffled. Person (0, 0): a
    quadratic prediction against a constant-velocity label, 6 frames with frame 6 missing and 7 .. 8
    after it (a 2-frame run: left out). Person (0, 1): 3 frames only (no jitter). Person (1, 0): the
    prediction is the label plus a cubic. Each has a still pelvis (joint 0) and five moving joints,
    so the means over the six joints are 5/6 of the moving joints'."""
    a, c, fps = 0.004, 2e-4, 25.0
    rows = []  # (sequence, track, frame, pred, label)
    p, g = _track(9, accel=a, seed=1), _track(9, seed=1)
    p, g = _with_pelvis(p), _with_pelvis(g)
    rows += [(0, 0, f, p[f], g[f]) for f in (0, 1, 2, 3, 4, 5, 7, 8)]
    p, g = _track(3, accel=2 * a, seed=2), _track(3, velocity=0.2, seed=2)
    p, g = _with_pelvis(p), _with_pelvis(g)
    rows += [(0, 1, f, p[f], g[f]) for f in range(3)]
    g = _track(5, velocity=0.03, accel=0.01, seed=3)
    p = g + _track(5, velocity=0.0, jerk=c, seed=3) - _track(1, velocity=0.0, seed=3)
    p, g = _with_pelvis(p), _with_pelvis(g)
    rows += [(1, 0, f, p[f], g[f]) for f in range(5)]
    order = np.random.default_rng(0).permutation(len(rows))
    rows = [rows[i] for i in order]
    s, k, f = (np.array([r[i] for r in rows]) for i in range(3))
    pred, label = torch.stack([r[3] for r in rows]), torch.stack([r[4] for r in rows])
    # The whole body moving with the pelvis, by anything, changes nothing.
    wobble = torch.randn(len(rows), 1, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    m = temporal_metrics(pred + wobble, label - wobble, s, k, f, fps, pelvis=0)

    assert (m.tracks, m.runs, m.frames) == (3, 3, 6 + 3 + 5)
    assert (m.jitter_tracks, m.jitter_runs, m.jitter_frames) == (2, 2, 6 + 5)
    assert m.fps == [fps]
    # Acceleration frames: 4 of (0, 0) at a, 1 of (0, 1) at 2a, 3 of (1, 0) (the cubic's 6 c t).
    jerk_acc = [6 * c * t for t in (1, 2, 3)]
    moving = 5 / 6
    assert m.accel_error_mm == pytest.approx(1000 * moving * (4 * a + 2 * a + sum(jerk_acc)) / 8, rel=1e-9)
    assert m.label_accel_mm == pytest.approx(
        1000 * moving * 3 * 0.01 / 8, rel=1e-9
    )  # only (1, 0)'s accelerate
    assert m.accel_mm > m.label_accel_mm
    # Jitter frames: 3 of (0, 0) (no jerk), 2 of (1, 0) at 6 c fps^3 (the label has none).
    assert m.jitter_km_s3 == pytest.approx(moving * 2 * 6 * c * fps**3 / 5 / 1000, rel=1e-9)
    assert m.label_jitter_km_s3 == pytest.approx(0.0, abs=1e-9)
    d = m.to_dict()
    assert json.loads(json.dumps(d)) == d
    assert "accel error" in format_temporal(d) and "3 tracks" in format_temporal(d)


def test_temporal_metrics_without_long_runs():
    x = torch.zeros(4, 2, 3)
    m = temporal_metrics(x, x, [0, 0, 0, 0], [0, 0, 1, 1], [0, 2, 0, 1], [30.0] * 4)
    assert (m.tracks, m.runs, m.frames) == (0, 0, 0)
    assert m.accel_error_mm is None and m.jitter_km_s3 is None
    assert "no run" in format_temporal(m.to_dict())


# ------------------------------------------------------------------------------------------------
# recovery evaluate on a fake sequence dataset (tests/synth/fakes.py)


@pytest.fixture(scope="module")
def sequence_eval(run_a, model, tmp_path_factory):
    from fakes import write_fake_sequences

    from recovery.cli import main

    root = tmp_path_factory.mktemp("temporal_eval")
    ds = write_fake_sequences(root / "ds", sequences=2, frames=6, fps=30.0, people=2, model=model)
    with one_thread():
        assert (
            main(["evaluate", str(run_a / "last.pt"), str(ds), "--out", str(root / "eval"), "--batch", "4"])
            == 0
        )
    return ds, json.loads((root / "eval" / "metrics.json").read_text())


def _label_rows(ds):
    """(sequence, track, frame, fps, (J, 3) pelvis-aligned float32 camera joints) per evaluated person,
    read straight from the samples' JSON (the dataset evaluates every person with a pixel)."""
    from recovery.eval.joints import EVAL_JOINTS
    from synth.dataset.index import DatasetIndex

    index = DatasetIndex(ds)
    rows = []
    for i in range(len(index)):
        doc = index.json(i)
        ev = [doc["keypoint_names"].index(n) for n in EVAL_JOINTS]
        pelvis = doc["keypoint_names"].index("pelvis")
        for q in doc["people"]:
            if q["pixels"] > 0:
                kp = np.asarray(q["keypoints_3d_cam"], np.float64)
                rel = (kp[ev] - kp[pelvis]).astype(np.float32).astype(np.float64)
                rows.append((doc["sequence"], q["track"], doc["frame"], doc["fps"], rel))
    index.close()
    return rows


def test_evaluate_reports_temporal_metrics_of_a_sequence_dataset(sequence_eval):
    from recovery.eval.evaluate import format_report

    ds, m = sequence_eval
    t = m["temporal"]
    rows = _label_rows(ds)
    assert m["people"] == len(rows)
    # Runs, and the labels' own acceleration and jitter, by a loop over the JSON labels.
    by_person: dict = {}
    for s, k, f, fps, x in rows:
        by_person.setdefault((s, k), {})[f] = (fps, x)
    runs = []  # (person, [(frame, fps, joints), ...])
    for person, frames in sorted(by_person.items()):
        for f in sorted(frames):
            if not runs or runs[-1][0] != person or f != runs[-1][1][-1][0] + 1:
                runs.append((person, []))
            runs[-1][1].append((f, *frames[f]))
    # Person 1 of sequence 1 leaves the image after two frames: too short a run, left out.
    assert sorted((len(r), person) for person, r in runs) == [
        (2, (1, 1)),
        (6, (0, 0)),
        (6, (0, 1)),
        (6, (1, 0)),
    ]
    long = [r for _, r in runs if len(r) >= 3]
    assert (t["tracks"], t["runs"], t["frames"]) == (3, 3, 18)
    assert (t["jitter_tracks"], t["jitter_runs"], t["jitter_frames"]) == (3, 3, 18)
    acc, jit = [], []
    for r in long:
        x = np.stack([e[2] for e in r])  # (L, J, 3)
        for i in range(1, len(r) - 1):
            acc.append(np.linalg.norm(x[i + 1] - 2 * x[i] + x[i - 1], axis=-1).mean())
        for i in range(1, len(r) - 2):
            d3 = x[i + 2] - 3 * x[i + 1] + 3 * x[i] - x[i - 1]
            jit.append(np.linalg.norm(d3, axis=-1).mean() * r[0][1] ** 3)
    assert t["label_accel_mm"] == pytest.approx(1000 * np.mean(acc), rel=1e-9)
    assert t["label_jitter_km_s3"] == pytest.approx(np.mean(jit) / 1000, rel=1e-9)
    assert t["fps"] == [30.0]
    for key in ("accel_error_mm", "accel_mm", "jitter_km_s3"):
        assert math.isfinite(t[key]) and t[key] >= 0, key
    # Per joint, | |a_P - a_G| - |a_G| | <= |a_P| (the triangle inequality), so on average too.
    assert abs(t["accel_error_mm"] - t["label_accel_mm"]) <= t["accel_mm"] + 1e-9
    assert "  temporal (3 tracks, 3 runs, 18 frames): accel error" in format_report(m)


def test_evaluate_of_single_images_has_no_temporal_section(run_a, fake_root, tmp_path):
    from recovery.eval.evaluate import evaluate

    with one_thread():
        m = evaluate(run_a / "last.pt", fake_root, tmp_path / "eval", batch=8, log=lambda *a: None)
    assert "temporal" not in m
