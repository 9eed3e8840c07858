"""3D keypoints of a scan without landmarks: multi-view renders, a 2D detector, robust triangulation.

Thesis Sec. 6.3.1 (stage 1 of registration): the scan is rendered from C cameras on a sphere
(:mod:`blsm.learn.markerless.multiview`), a 2D keypoint detector runs on every view (:mod:`blsm.pose2d`:
MediaPipe Pose by default), and each keypoint is triangulated from the views that see it (Eq. 6.3,
``L_hat_i = P_i L`` for all views i, solved linearly), then 3 times the 25 % of views with the largest
reprojection error are removed and ``L`` re-estimated; the keypoint's confidence is the mean
visibility of the views that survive. The registration's keypoint term (Eq. 6.4) weighs by it.

Details that the thesis leaves open, as done here:

* **Linear triangulation** (:func:`triangulate_dlt`): the homogeneous DLT, rows ``u P_3 - P_1`` and
  ``v P_3 - P_2`` per view (pixels), each normalised to unit length, solved by SVD; unweighted as Eq. 6.3.
* **Views used**: those whose detection has visibility >= ``min_visibility`` (0.5) for the keypoint
  and lies inside the image. With n views, each round drops ``floor(0.25 n)`` of them (at least one
  while more than ``min_views`` = 2 remain): 18 -> 14 -> 11 -> 9 views. A keypoint with fewer than 2
  views, or whose surviving views' median reprojection error exceeds ``max_error_px``, is NaN.
* **Left/right swaps** (:func:`fix_swaps`): BlazePose names sides by the person's left and right,
  which holds for views from behind, but a detector can flip sides (none did in our measurement).
  After a first robust triangulation of all 33 landmarks, each view's detections are compared with
  the consensus in both assignments (its own, and left and right exchanged); a view whose swapped
  assignment reprojects with less than ``swap_ratio`` (0.5) times the median error of its own is
  swapped, and everything is triangulated again. A view that flips only some pairs is left as is
  (the robust drop handles it). If most views flipped, the consensus itself would be the mirror
  image; that is not detected.
* **No person**: when no view finds a person, :func:`scan_keypoints` raises ``ValueError("FILE: no
  person found in any of the C views")``.

The output keypoints are BLSM keypoint names (:data:`MEDIAPIPE_TO_BLSM`, ``blsm.load().keypoint_names``);
only landmarks whose meaning matches a BLSM keypoint are mapped (docs/markerless.md has the table
and the measured offsets: BlazePose's hips, for instance, are not the hip joint centres).
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from blsm.camera import Camera
from blsm.learn.markerless.multiview import ViewConfig
from blsm.pose2d.detectors import MEDIAPIPE_MIRROR, MEDIAPIPE_NAMES, PoseDetector

if TYPE_CHECKING:
    from blsm.learn.scans.format import Scan
    from blsm.model import BLSM

MEDIAPIPE_TO_BLSM: dict[str, str] = {
    "nose": "nose",
    "left_eye": "left_eye",
    "right_eye": "right_eye",
    "left_ear": "left_ear",
    "right_ear": "right_ear",
    "left_shoulder": "left_shoulder",
    "right_shoulder": "right_shoulder",
    "left_elbow": "left_elbow",
    "right_elbow": "right_elbow",
    "left_wrist": "left_wrist",
    "right_wrist": "right_wrist",
    "left_hip": "left_hip",
    "right_hip": "right_hip",
    "left_knee": "left_knee",
    "right_knee": "right_knee",
    "left_ankle": "left_ankle",
    "right_ankle": "right_ankle",
    "left_heel": "heel_l",
    "right_heel": "heel_r",
    "left_foot_index": "toe_tip_l",
    "right_foot_index": "toe_tip_r",
}
"""BlazePose landmark -> BLSM keypoint, for the landmarks whose meaning matches (21 of 33). Not
mapped: the inner/outer eye corners, the mouth corners (no BLSM keypoint), and the pinky, index and
thumb landmarks (BlazePose's rough hand points; BLSM's ``hand_tip`` is the middle finger's tip)."""

BLSM_NAMES: tuple[str, ...] = tuple(MEDIAPIPE_TO_BLSM.values())
_MP_INDEX = np.array([MEDIAPIPE_NAMES.index(n) for n in MEDIAPIPE_TO_BLSM])


@dataclass(frozen=True)
class MarkerlessConfig:
    """Views, detector thresholds and the robust triangulation (Eq. 6.3).

    Attributes:
        views: the cameras and renders (:class:`blsm.learn.markerless.multiview.ViewConfig`).
        min_visibility: a detection counts for a keypoint at this visibility or above.
        drop_fraction: the fraction of views dropped per round (0.25, Sec. 6.3.1).
        rounds: rounds of dropping (3).
        min_views: fewest views a keypoint is triangulated from (2).
        max_error_px: a keypoint whose surviving views' median reprojection error is larger is NaN.
        swap_check: test each view for a left/right flip against the consensus (:func:`fix_swaps`).
        swap_ratio: a view is swapped if its swapped error is below this times its own.
    """

    views: ViewConfig = field(default_factory=ViewConfig)
    min_visibility: float = 0.5
    drop_fraction: float = 0.25
    rounds: int = 3
    min_views: int = 2
    max_error_px: float = 20.0
    swap_check: bool = True
    swap_ratio: float = 0.5

    def __post_init__(self) -> None:
        if not 0.0 <= self.drop_fraction < 1.0 or self.rounds < 0 or self.min_views < 2:
            raise ValueError("MarkerlessConfig needs 0 <= drop_fraction < 1, rounds >= 0, min_views >= 2")


@dataclass
class ViewResults:
    """What each view contributed.

    Attributes:
        K: (C, 3, 3), R: (C, 3, 3), t: (C, 3): the OpenCV cameras (pixels; world to camera, metres).
        size: (width, height) of the images, pixels.
        boxes: (C, 4) the boxes given to the detector, pixels.
        detections: (C, 33, 3) the detector's landmarks (x, y, visibility), NaN where no person.
        found: (C,) bool: the detector found a person.
        swapped: (C,) bool: the view's left and right were exchanged (:func:`fix_swaps`).
        used: (C, K) bool: the view survived for the output keypoint.
        error_px: (C, K) reprojection error of each view's detection of the final keypoint, pixels
            (NaN where the view did not detect it above the visibility threshold).
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    size: tuple[int, int]
    boxes: np.ndarray
    detections: np.ndarray
    found: np.ndarray
    swapped: np.ndarray
    used: np.ndarray
    error_px: np.ndarray


@dataclass
class ScanKeypoints:
    """Triangulated keypoints of one scan.

    Attributes:
        names: K BLSM keypoint names (:data:`BLSM_NAMES`, K = 21).
        points: (K, 3) float64 world positions, metres; NaN rows were not triangulated.
        confidence: (K,) mean visibility of the surviving views (0 where NaN).
        num_views: (K,) views that survived.
        views: C, views rendered.
        views_with_person: views where the detector found a person.
        detector: the detector's name.
        per_view: :class:`ViewResults`.
        images: the C rendered views (H, W, 3) uint8, kept only if asked (``keep_images``).
    """

    names: list[str]
    points: np.ndarray
    confidence: np.ndarray
    num_views: np.ndarray
    views: int
    views_with_person: int
    detector: str
    per_view: ViewResults
    images: list[np.ndarray] | None = None

    def to_json(self) -> dict[str, Any]:
        """A JSON-able summary (no per-view arrays except found/swapped)."""
        return {
            "detector": self.detector,
            "views": self.views,
            "views_with_person": self.views_with_person,
            "swapped_views": int(self.per_view.swapped.sum()),
            "keypoints": {
                n: None if not np.isfinite(p).all() else {"xyz": [round(float(x), 5) for x in p],
                                                          "confidence": round(float(c), 4), "views": int(v)}
                for n, p, c, v in zip(self.names, self.points, self.confidence, self.num_views, strict=True)
            },
        }


# ----------------------------------------------------------------------------------------------
# Triangulation (Eq. 6.3)


def projection_matrices(cameras: list[Camera]) -> np.ndarray:
    """(C, 3, 4) ``K [R | t]`` of each camera (world metres -> homogeneous pixels)."""
    return np.stack([c.K @ np.concatenate([c.R, c.t[:, None]], axis=1) for c in cameras])


def triangulate_dlt(P: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Linear triangulation of one point from n >= 2 views (Eq. 6.3, the homogeneous DLT).

    Rows ``u P_3 - P_1`` and ``v P_3 - P_2`` per view, each normalised to unit length (so views
    count equally whatever their scale), solved by SVD.

    Args:
        P: (n, 3, 4) projection matrices (pixels).
        uv: (n, 2) pixel positions.

    Returns:
        (3,) the point, metres (NaN if the solution is at infinity).
    """
    rows = np.concatenate([uv[:, :1] * P[:, 2] - P[:, 0], uv[:, 1:] * P[:, 2] - P[:, 1]])  # (2n, 4)
    rows = rows / np.linalg.norm(rows, axis=1, keepdims=True)
    x = np.linalg.svd(rows)[2][-1]
    if abs(x[3]) < 1e-12:
        return np.full(3, np.nan)
    return x[:3] / x[3]


def reprojection_errors(P: np.ndarray, uv: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(n,) pixel distances between ``uv`` (n, 2) and the projections of ``X`` (3,) by ``P`` (n, 3, 4)."""
    h = P @ np.append(X, 1.0)  # (n, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.linalg.norm(h[:, :2] / h[:, 2:] - uv, axis=1)


def robust_triangulate(
    P: np.ndarray, uv: np.ndarray, cfg: MarkerlessConfig = MarkerlessConfig()
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 6.3 with the thesis's outlier rounds: triangulate, drop the worst 25 % of views, repeat.

    Args:
        P: (n, 3, 4) projection matrices of the views that detected the keypoint.
        uv: (n, 2) their detections, pixels.
        cfg: ``drop_fraction``, ``rounds``, ``min_views``.

    Returns:
        (point (3,) metres or NaN, kept (n,) bool: the views that survived).
    """
    keep = np.ones(len(P), dtype=bool)
    if len(P) < cfg.min_views:
        return np.full(3, np.nan), np.zeros(len(P), dtype=bool)
    X = triangulate_dlt(P, uv)
    for _ in range(cfg.rounds):
        n = int(keep.sum())
        drop = min(max(1, math.floor(cfg.drop_fraction * n)), n - cfg.min_views)
        if drop <= 0 or not np.isfinite(X).all():
            break
        idx = np.flatnonzero(keep)
        err = reprojection_errors(P[idx], uv[idx], X)
        err = np.where(np.isfinite(err), err, np.inf)
        keep[idx[np.argsort(err, kind="stable")[n - drop :]]] = False
        X = triangulate_dlt(P[keep], uv[keep])
    return X, keep


def triangulate_all(
    P: np.ndarray, detections: np.ndarray, size: tuple[int, int], cfg: MarkerlessConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robustly triangulate every landmark of (C, M, 3) detections (x, y, visibility; NaN = none).

    Returns:
        (points (M, 3) metres or NaN, kept (C, M) bool, confidence (M,) mean surviving visibility).
    """
    c, m, _ = detections.shape
    with np.errstate(invalid="ignore"):
        good = (detections[..., 2] >= cfg.min_visibility) & np.isfinite(detections).all(-1)
        good &= (detections[..., 0] >= 0) & (detections[..., 0] < size[0])
        good &= (detections[..., 1] >= 0) & (detections[..., 1] < size[1])
    points = np.full((m, 3), np.nan)
    kept = np.zeros((c, m), dtype=bool)
    conf = np.zeros(m)
    for k in range(m):
        views = np.flatnonzero(good[:, k])
        X, keep = robust_triangulate(P[views], detections[views, k, :2], cfg)
        if not np.isfinite(X).all() or keep.sum() < cfg.min_views:
            continue
        err = reprojection_errors(P[views[keep]], detections[views[keep], k, :2], X)
        if np.median(err) > cfg.max_error_px:
            continue
        points[k] = X
        kept[views[keep], k] = True
        conf[k] = float(detections[views[keep], k, 2].mean())
    return points, kept, conf


def fix_swaps(
    P: np.ndarray, detections: np.ndarray, consensus: np.ndarray, cfg: MarkerlessConfig,
    mirror: tuple[int, ...] | list[int] = MEDIAPIPE_MIRROR,
) -> np.ndarray:
    """(C,) bool: views whose left/right-exchanged detections fit the consensus clearly better.

    For each view, the median reprojection error over its visible landmarks that have a left/right
    counterpart, in its own assignment and with left and right exchanged; swapped if the exchanged
    one is below ``swap_ratio`` times the own one (and at least 3 such landmarks are visible).
    ``mirror``: each landmark's left/right counterpart (default BlazePose's).
    """
    mirror = np.asarray(mirror)
    paired = np.array([i for i, j in enumerate(mirror) if i != j])
    out = np.zeros(len(P), dtype=bool)
    ok_x = np.isfinite(consensus).all(1)
    for v in range(len(P)):
        det = detections[v]
        with np.errstate(invalid="ignore"):
            vis = paired[(det[paired, 2] >= cfg.min_visibility) & ok_x[paired] & ok_x[mirror[paired]]]
        if len(vis) < 3:
            continue
        own = np.median([reprojection_errors(P[v : v + 1], det[k : k + 1, :2], consensus[k])[0] for k in vis])
        swp = np.median([reprojection_errors(P[v : v + 1], det[k : k + 1, :2], consensus[mirror[k]])[0]
                         for k in vis])
        out[v] = swp < cfg.swap_ratio * own
    return out


# ----------------------------------------------------------------------------------------------
# The scan's keypoints


def scan_keypoints(
    scan: Scan,
    detector: PoseDetector | None = None,
    config: MarkerlessConfig = MarkerlessConfig(),
    where: str | None = None,
    keep_images: bool = False,
) -> ScanKeypoints:
    """3D keypoints of a scan from multi-view renders and a 2D detector (Sec. 6.3.1, Eq. 6.3).

    Args:
        scan: a :class:`blsm.learn.scans.format.Scan` (its ``colors`` are rendered if present).
        detector: a :class:`blsm.pose2d.detectors.PoseDetector`; default MediaPipe Pose
            (:class:`blsm.pose2d.detectors.MediaPipeDetector`, needs ``.venv-reference``).
        config: views and thresholds.
        where: names the scan in errors (default ``scan.meta["source"]`` or ``["id"]``).
        keep_images: keep the rendered views in the result (``images``).

    Returns:
        :class:`ScanKeypoints` with the :data:`BLSM_NAMES` keypoints.

    Raises:
        ValueError: ``"<where>: no person found in any of the C views"``, or the detector's error.
    """
    from blsm.learn.markerless.multiview import render_scan
    from blsm.pose2d.detectors import MediaPipeDetector

    where = where or str(scan.meta.get("source", scan.meta.get("id", "scan")))
    detector = MediaPipeDetector() if detector is None else detector
    cameras, boxes, images = render_scan(scan.vertices, scan.faces, scan.colors, config.views)
    found_list = detector(images, boxes, cameras)
    if len(found_list) != len(cameras):
        raise ValueError(f"{where}: the detector answered {len(found_list)} of {len(cameras)} views")
    result = keypoints_from_detections(found_list, cameras, boxes, config, getattr(detector, "name", "?"), where)
    result.images = images if keep_images else None
    return result


def keypoints_from_detections(
    found_list: list[np.ndarray | None],
    cameras: list[Camera],
    boxes: np.ndarray,
    config: MarkerlessConfig = MarkerlessConfig(),
    detector_name: str = "?",
    where: str = "scan",
) -> ScanKeypoints:
    """The triangulation half of :func:`scan_keypoints`: 33-landmark detections per view -> keypoints."""
    c = len(cameras)
    size = (cameras[0].width, cameras[0].height)
    dets = np.full((c, len(MEDIAPIPE_NAMES), 3), np.nan)
    for i, d in enumerate(found_list):
        if d is not None:
            dets[i] = np.asarray(d, np.float64).reshape(len(MEDIAPIPE_NAMES), 3)
    found = np.array([d is not None for d in found_list])
    if not found.any():
        raise ValueError(f"{where}: no person found in any of the {c} views")
    P = projection_matrices(cameras)
    points, kept, conf, swapped, err = triangulate_views(P, dets, found, size, config, MEDIAPIPE_MIRROR)
    per_view = ViewResults(
        K=np.stack([cam.K for cam in cameras]), R=np.stack([cam.R for cam in cameras]),
        t=np.stack([cam.t for cam in cameras]), size=size, boxes=np.asarray(boxes, np.float64),
        detections=dets, found=found, swapped=swapped, used=kept[:, _MP_INDEX], error_px=err[:, _MP_INDEX],
    )  # fmt: skip
    return ScanKeypoints(
        names=list(BLSM_NAMES),
        points=points[_MP_INDEX],
        confidence=conf[_MP_INDEX],
        num_views=kept[:, _MP_INDEX].sum(0),
        views=c,
        views_with_person=int(found.sum()),
        detector=detector_name,
        per_view=per_view,
    )


def triangulate_views(
    P: np.ndarray, dets: np.ndarray, found: np.ndarray, size: tuple[int, int], config: MarkerlessConfig,
    mirror: tuple[int, ...] | list[int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`triangulate_all`, then :func:`fix_swaps` (swapped views' ``dets`` are exchanged in place
    and everything triangulated again), then each view's reprojection error of every landmark.

    Returns:
        (points (M, 3), kept (C, M), confidence (M,), swapped (C,), error_px (C, M) NaN where unseen).
    """
    points, kept, conf = triangulate_all(P, dets, size, config)
    swapped = np.zeros(len(P), dtype=bool)
    if config.swap_check:
        swapped = fix_swaps(P, dets, points, config, mirror)
        if swapped.any():
            dets[swapped] = dets[swapped][:, list(mirror)]
            points, kept, conf = triangulate_all(P, dets, size, config)
    err = np.full(kept.shape, np.nan)
    for k in range(dets.shape[1]):
        vis = found & (dets[:, k, 2] >= config.min_visibility)
        if np.isfinite(points[k]).all() and vis.any():
            err[vis, k] = reprojection_errors(P[vis], dets[vis, k, :2], points[k])
    return points, kept, conf, swapped, err


def true_keypoints(scan: Scan, model: BLSM, names: list[str] | tuple[str, ...] = BLSM_NAMES) -> np.ndarray:
    """(K, 3) the true BLSM keypoints ``names`` of a synthetic scan, metres.

    Surface keypoints (face, heels, toe tips) from ``gt_points`` through the model's
    ``keypoint_vertices`` / ``keypoint_weights`` (exact: the same embedding as every template
    vertex); joint keypoints from ``gt_joints``, the posed Anny bone heads the BLSM joints were built
    from (:mod:`blsm.learn.scans.population`; exact by the same construction as the model's skeleton).

    Raises:
        ValueError: if the scan has no ``gt_points`` / ``gt_joints`` (not a synthetic scan).
    """
    if scan.gt_points is None or scan.gt_joints is None:
        raise ValueError(f"{scan.meta.get('id', 'scan')}: no gt_points / gt_joints (not a population scan)")
    out = np.zeros((len(names), 3))
    kj = model.keypoint_joint.cpu().numpy()
    kv = model.keypoint_vertices.cpu().numpy()
    kw = model.keypoint_weights.double().cpu().numpy()
    for i, n in enumerate(names):
        k = model.keypoint_names.index(n)
        if kj[k] >= 0:
            out[i] = scan.gt_joints[kj[k]]
        else:
            out[i] = (scan.gt_points[kv[k]].astype(np.float64) * kw[k][:, None]).sum(0)
    return out


def mediapipe_points(blsm_points: np.ndarray, names: list[str] | tuple[str, ...] = BLSM_NAMES) -> np.ndarray:
    """(33, 3) BlazePose-ordered world points from BLSM keypoints (K, 3) ``names``; NaN for the
    landmarks without a BLSM keypoint (for :class:`blsm.pose2d.detectors.ProjectedDetector`)."""
    out = np.full((len(MEDIAPIPE_NAMES), 3), np.nan)
    inv = {b: m for m, b in MEDIAPIPE_TO_BLSM.items()}
    for n, p in zip(names, blsm_points, strict=True):
        if n in inv:
            out[MEDIAPIPE_NAMES.index(inv[n])] = p
    return out


# ----------------------------------------------------------------------------------------------
# Pictures and the debugging command

_SKELETON = (("left_shoulder", "right_shoulder"), ("left_shoulder", "left_elbow"), ("left_elbow", "left_wrist"),
             ("right_shoulder", "right_elbow"), ("right_elbow", "right_wrist"), ("left_shoulder", "left_hip"),
             ("right_shoulder", "right_hip"), ("left_hip", "right_hip"), ("left_hip", "left_knee"),
             ("left_knee", "left_ankle"), ("right_hip", "right_knee"), ("right_knee", "right_ankle"),
             ("left_ankle", "left_heel"), ("left_heel", "left_foot_index"), ("right_ankle", "right_heel"),
             ("right_heel", "right_foot_index"), ("nose", "left_eye"), ("nose", "right_eye"))


def contact_sheet(
    images: list[np.ndarray], result: ScanKeypoints, path: str | Path, views: list[int] | None = None,
    cols: int = 6, min_visibility: float = 0.5,
) -> Path:
    """PNG of views with the detections drawn: the person's left in blue, right in red, middle green;
    hollow circles where visibility is below ``min_visibility``; the box in grey; the reprojected
    3D keypoints as small white crosses; "no person" or "swapped" written on the view."""
    from PIL import Image, ImageDraw

    from blsm.render import save_png

    views = list(range(len(images))) if views is None else views
    h, w = images[0].shape[:2]
    rows = -(-len(views) // cols)
    sheet = Image.new("RGB", (min(cols, len(views)) * w, rows * h), (255, 255, 255))
    P = projection_matrices([Camera(K, R, t, *result.per_view.size) for K, R, t in
                             zip(result.per_view.K, result.per_view.R, result.per_view.t, strict=True)])
    for n, v in enumerate(views):
        tile = Image.fromarray(images[v])
        d = ImageDraw.Draw(tile)
        d.rectangle([float(x) for x in result.per_view.boxes[v]], outline=(150, 150, 150))
        det = result.per_view.detections[v]
        if not result.per_view.found[v]:
            d.text((6, 6), f"view {v}: no person", fill=(255, 40, 40))
        else:
            for a, b in _SKELETON:
                pa, pb = det[MEDIAPIPE_NAMES.index(a)], det[MEDIAPIPE_NAMES.index(b)]
                if min(pa[2], pb[2]) >= min_visibility:
                    d.line([tuple(pa[:2]), tuple(pb[:2])], fill=(240, 240, 240), width=1)
            for name, p in zip(MEDIAPIPE_NAMES, det, strict=True):
                col = (40, 90, 255) if name.startswith("left") else (255, 40, 40) if name.startswith("right") else (0, 200, 0)
                box = [p[0] - 3, p[1] - 3, p[0] + 3, p[1] + 3]
                d.ellipse(box, fill=col if p[2] >= min_visibility else None, outline=col)
            d.text((6, 6), f"view {v}" + (" swapped" if result.per_view.swapped[v] else ""), fill=(0, 0, 0))
        for X in result.points[np.isfinite(result.points).all(1)]:
            hp = P[v] @ np.append(X, 1.0)
            u, q = hp[:2] / hp[2]
            d.line([(u - 3, q), (u + 3, q)], fill=(255, 255, 255))
            d.line([(u, q - 3), (u, q + 3)], fill=(255, 255, 255))
        sheet.paste(tile, ((n % cols) * w, (n // cols) * h))
    return save_png(np.asarray(sheet), path)


def add_parser(sub: Any, help_text: str, wrap: Callable) -> None:
    """``blsm scan-keypoints SCAN --out JSON``: the markerless keypoints of one scan (for debugging);
    ``wrap(name, run)`` turns a ValueError into one line and exit 2."""
    p = sub.add_parser("scan-keypoints", help=help_text)
    p.add_argument("scan", type=Path, help="a blsm-scan .npz or an OBJ / PLY / GLB mesh (vertex colours used)")
    p.add_argument("--out", type=Path, required=True, help="JSON file of the keypoints")
    p.add_argument("--views", type=int, default=ViewConfig.views)
    p.add_argument("--resolution", type=int, default=ViewConfig.resolution)
    p.add_argument("--sheet", type=Path, default=None, help="PNG of the views with the detections drawn")
    p.add_argument("--python", default=None, help="the MediaPipe environment's python (default .venv-reference)")
    p.set_defaults(func=wrap("scan-keypoints", _cmd))


def _cmd(args: argparse.Namespace) -> int:
    from blsm.io import atomic_write
    from blsm.learn.scans.format import load_scan
    from blsm.pose2d.detectors import MediaPipeDetector

    scan = load_scan(args.scan)
    detector = MediaPipeDetector(args.python)
    detector.command()  # a missing environment fails before the renders
    cfg = MarkerlessConfig(views=ViewConfig(views=args.views, resolution=args.resolution))
    result = scan_keypoints(scan, detector, cfg, str(args.scan), args.sheet is not None)
    with atomic_write(args.out, "w") as fh:
        json.dump({"scan": str(args.scan), "config": asdict(cfg), **result.to_json()}, fh, indent=1)
    if args.sheet is not None:
        contact_sheet(result.images, result, args.sheet)
    ok = int(np.isfinite(result.points).all(1).sum())
    print(f"{args.scan}: {ok}/{len(result.names)} keypoints from {result.views_with_person}/{result.views} views "
          f"with a person ({int(result.per_view.swapped.sum())} swapped) -> {args.out}")
    return 0
