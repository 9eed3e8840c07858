"""A_kp of Eq. 6.4 learnt for a detector: each detector keypoint as a few mesh vertices.

Thesis Sec. 6.3.1 writes the keypoint term of Eq. 6.4 as ``A_kp BLSM(c_b; theta) - L_t`` with
A_kp "a linear matrix that regresses keypoints from a BLSM mesh". Mapping a detector's keypoints by
name onto the model's joints (:data:`blsm.learn.markerless.keypoints.MEDIAPIPE_TO_BLSM`) leaves the
detector's own definitions out: BlazePose's hips, shoulders, ears and toes sit 1-4 cm from the
joints of the same name (docs/markerless.md). Here A_kp is learnt instead, the way SMPL's joint
regressor was: on training scans with known correspondence (stand-in scans carry ``gt_points``,
the true position of every template vertex), each keypoint's triangulated detections are
regressed on the posed vertices,

    L_k ~ sum_i w_ki V_{v_ki},   sum_i w_ki = 1,

with 3 vertices per keypoint (the best triplet among the vertices nearest to the detections,
with free weights that sum to one, so the point may lie inside the body). The result is a :class:`blsm.learn.registration.keypoint_fit.KeypointSet` of surface-type keypoints.

The file (``.npz``, format ``blsm-keypoint-regressor`` v1): ``names`` (K,), ``vertices`` (K, 3)
int64 template vertex indices, ``weights`` (K, 3) float64, ``meta`` JSON (training scans, residual
per keypoint in mm).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm.io import read_versioned_npz, write_versioned_npz
from blsm.learn.registration.keypoint_fit import KeypointSet

FORMAT = "blsm-keypoint-regressor"
FORMAT_VERSION = 1


def fit_keypoint_regressor(
    points: np.ndarray, vertices: np.ndarray, names: list[str], candidates: int = 48,
    max_weight: float = 2.0,
) -> tuple[KeypointSet, dict[str, Any]]:
    """Learn A_kp from N training scans: per keypoint the best vertex triplet with affine weights.

    For every triplet of the ``candidates`` vertices nearest to the detections (on average over the
    scans), the weights ``w`` (sum 1) minimising ``sum_n ||sum_i w_i V_n,i - L_n||^2`` are solved in
    closed form; the triplet with the smallest residual whose weights stay within ``max_weight`` in
    absolute value (no far extrapolation) is kept.

    Args:
        points: (N, K, 3) detected (triangulated) keypoints, metres; NaN rows = not found.
        vertices: (N, V, 3) the true posed template vertices of the same scans (``gt_points``).
        names: the K keypoint names.
        candidates: vertices considered per keypoint.
        max_weight: largest allowed absolute weight.

    Returns:
        (the keypoint set, a report: per keypoint the training residual RMS in mm and the scans used).
    """
    from itertools import combinations

    points = np.asarray(points, np.float64)
    vertices = np.asarray(vertices, np.float64)
    n, k = points.shape[:2]
    if vertices.shape[0] != n or vertices.ndim != 3 or vertices.shape[2] != 3:
        raise ValueError(f"vertices must be (N={n}, V, 3), got {vertices.shape}")
    if len(names) != k:
        raise ValueError(f"{len(names)} names for {k} keypoints")
    out_v = np.zeros((k, 3), np.int64)
    out_w = np.zeros((k, 3))
    report: dict[str, Any] = {"residual_mm": {}, "scans": {}}
    for j in range(k):
        ok = np.isfinite(points[:, j]).all(1)
        if ok.sum() < 3:
            raise ValueError(f"keypoint {names[j]}: found in {int(ok.sum())} training scans (need >= 3)")
        y, x = points[ok, j], vertices[ok]  # (M, 3), (M, V, 3)
        cand = np.argsort(np.linalg.norm(x - y[:, None], axis=2).mean(0))[:candidates]
        tri = np.array(list(combinations(cand, 3)))  # (T, 3)
        xs = x[:, tri]  # (M, T, 3 vertices, 3 xyz)
        base = xs[:, :, 0]  # (M, T, 3)
        d = xs[:, :, 1:] - base[:, :, None]  # (M, T, 2, 3)
        r = y[:, None] - base  # (M, T, 3)
        ata = np.einsum("mtac,mtbc->tab", d, d)  # (T, 2, 2)
        atb = np.einsum("mtac,mtc->ta", d, r)  # (T, 2)
        z = np.linalg.solve(ata + 1e-12 * np.eye(2), atb[..., None])[..., 0]  # (T, 2)
        w = np.concatenate([1.0 - z.sum(1, keepdims=True), z], axis=1)  # (T, 3)
        res = ((np.einsum("mtvc,tv->mtc", xs, w) - y[:, None]) ** 2).sum(2).mean(0)  # (T,)
        res[np.abs(w).max(1) > max_weight] = np.inf
        best = int(np.argmin(res))
        out_v[j], out_w[j] = tri[best], w[best]
        report["residual_mm"][names[j]] = float(np.sqrt(res[best]) * 1000)
        report["scans"][names[j]] = int(ok.sum())
    kps = KeypointSet(list(names), torch.full((k,), -1, dtype=torch.long), torch.as_tensor(out_v),
                      torch.as_tensor(out_w, dtype=torch.float32))
    return kps, report


def save_keypoint_regressor(kps: KeypointSet, path: str | Path, meta: dict[str, Any]) -> Path:
    """Write the regressor file (format in the module docstring)."""
    return write_versioned_npz(path, FORMAT, FORMAT_VERSION, {
        "names": np.array(kps.names), "vertices": kps.vertices.numpy().astype(np.int64),
        "weights": kps.bary.double().numpy(), "meta": np.array(json.dumps(meta)),
    })


def load_keypoint_regressor(path: str | Path, num_template_vertices: int) -> KeypointSet:
    """Read a regressor file; ValueError naming the file when it is not one or does not fit the model."""
    a = read_versioned_npz(path, FORMAT, FORMAT_VERSION, "keypoint regressor")
    try:
        names = [str(s) for s in a["names"]]
        v = np.asarray(a["vertices"], np.int64)
        w = np.asarray(a["weights"], np.float64)
    except KeyError as e:
        raise ValueError(f"{path}: keypoint regressor lacks {e}") from None
    if v.shape != (len(names), 3) or w.shape != v.shape or not np.isfinite(w).all():
        raise ValueError(f"{path}: vertices and weights must be ({len(names)}, 3) and finite")
    if v.min() < 0 or v.max() >= num_template_vertices:
        raise ValueError(f"{path}: vertex indices outside the model's {num_template_vertices} vertices")
    return KeypointSet(names, torch.full((len(names),), -1, dtype=torch.long), torch.as_tensor(v),
                       torch.as_tensor(w, dtype=torch.float32))


DEFAULT_REGRESSOR = Path(__file__).resolve().parents[2] / "data" / "keypoint_regressor_mediapipe.npz"
"""The packaged A_kp for MediaPipe's 21 mapped keypoints, learnt by :func:`main` on 20 stand-in scans
(``blsm scans``-style population, seed 3201: 10 subjects, rest and one posed scan each; held out from
every measurement in docs/markerless.md)."""


def main(argv: list[str] | None = None) -> int:
    """``python -m blsm.learn.markerless.keypoint_regressor SCAN.npz ... --out FILE``: MediaPipe keypoints of
    training stand-in scans (they need ``gt_points`` and vertex colours), then the regressor."""
    import argparse
    import sys

    from blsm.learn.markerless.keypoints import scan_keypoints
    from blsm.learn.scans.format import load_scan

    ap = argparse.ArgumentParser(prog="python -m blsm.learn.markerless.keypoint_regressor")
    ap.add_argument("scans", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    try:
        pts, gts, names = [], [], None
        for p in args.scans:
            scan = load_scan(p)
            if scan.gt_points is None:
                raise ValueError(f"{p}: no gt_points (a training scan needs its true correspondence)")
            k = scan_keypoints(scan, where=str(p))
            pts.append(k.points)
            gts.append(np.asarray(scan.gt_points, np.float64))
            names = list(k.names)
            print(f"{p}: {int(np.isfinite(k.points).all(1).sum())} keypoints", file=sys.stderr, flush=True)
        kps, report = fit_keypoint_regressor(np.stack(pts), np.stack(gts), names)
    except ValueError as exc:
        print(f"keypoint_regressor: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    save_keypoint_regressor(kps, args.out, {"scans": [str(p) for p in args.scans], **report})
    print(f"wrote {args.out}: training residual {np.mean(list(report['residual_mm'].values())):.1f} mm "
          "(mean over keypoints)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
