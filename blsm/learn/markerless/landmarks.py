"""Scan landmarks without a human: the learnt landmark detector on multi-view renders, triangulated.

The markerless route of thesis Sec. 6.3 with a different detector: instead of a photograph-trained
body-keypoint detector (MediaPipe's 33 BlazePose landmarks, :mod:`blsm.learn.markerless.keypoints`), the
detector of :mod:`blsm.pose2d.landmark_net` finds the 74 anthropometric landmarks of
``blsm/data/landmarks.yaml`` in each of the C renders (:mod:`blsm.learn.markerless.multiview`). Each landmark is
triangulated exactly as MediaPipe's keypoints are (Eq. 6.3 with three rounds that drop the worst
25 % of the views, :func:`blsm.learn.markerless.keypoints.triangulate_all`), views whose left and right came
out exchanged are found and undone (:func:`blsm.learn.markerless.keypoints.fix_swaps`), and the result fills
the scan's ``landmarks``. The scan then goes through the landmark registration unchanged
(Eqs. 5.13-5.25): the located landmarks stand where CAESAR's hand-placed ones stood.

A landmark counts in a view when the detector's heatmap peak is at least ``min_confidence`` (0.3;
the peaks of the training targets are 1, those of hidden landmarks are lower); a view shows a person
when at least half of the landmarks count in it (the detector is also trained on scenes without a
person, where it must find nothing); a scan without such a view is an error; a landmark with fewer
than 2 surviving views, or whose surviving views disagree by more than ``max_error_px`` (median
reprojection error), is not located (NaN), as a landmarker leaves out what they cannot find.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from blsm.learn.markerless.keypoints import (
    MarkerlessConfig,
    ScanKeypoints,
    ViewResults,
    projection_matrices,
    triangulate_views,
)
from blsm.learn.scans.format import Scan


@dataclass(frozen=True)
class LandmarkDetectionConfig:
    """Views, thresholds and triangulation of :func:`detect_landmarks`.

    Attributes:
        markerless: views and triangulation (:class:`MarkerlessConfig`); its ``min_visibility`` is
            replaced by ``min_confidence``.
        min_confidence: a view's detection counts at this heatmap peak or above.
        person_fraction: a view shows a person when at least this fraction of the landmarks count
            in it (the detector was trained to find nothing in scenes without a person); the other
            views are not used at all.
    """

    markerless: MarkerlessConfig = MarkerlessConfig()
    min_confidence: float = 0.3
    person_fraction: float = 0.5


def detect_landmarks(
    scan: Scan,
    detector=None,  # noqa: ANN001 (a blsm.pose2d.landmark_net.LandmarkDetector)
    config: LandmarkDetectionConfig = LandmarkDetectionConfig(),
    where: str | None = None,
    keep_images: bool = False,
) -> ScanKeypoints:
    """The scan's landmarks from its renders (see the module docstring).

    Args:
        scan: a :class:`Scan` (its ``colors`` are rendered when present).
        detector: a :class:`blsm.pose2d.landmark_net.LandmarkDetector` (default: the packaged one).
        config: views and thresholds.
        where: names the scan in errors.
        keep_images: keep the renders in the result.

    Returns:
        :class:`ScanKeypoints` with the detector's landmark names (NaN rows: not located).

    Raises:
        ValueError: ``"<where>: no person found in any of the C views"``.
    """
    from blsm.learn.markerless.multiview import render_scan
    from blsm.pose2d.landmark_net import LandmarkDetector, mirror_index

    where = where or str(scan.meta.get("source", scan.meta.get("id", "scan")))
    detector = LandmarkDetector() if detector is None else detector
    mcfg = replace(config.markerless, min_visibility=config.min_confidence)
    cameras, boxes, images = render_scan(scan.vertices, scan.faces, scan.colors, mcfg.views)
    dets = np.stack(detector(images, boxes, cameras)).astype(np.float64)  # (C, L, 3)
    names = list(detector.names)
    found = (dets[..., 2] >= mcfg.min_visibility).mean(1) >= config.person_fraction
    if not found.any():
        raise ValueError(f"{where}: no person found in any of the {len(cameras)} views")
    dets[~found] = np.nan
    P = projection_matrices(cameras)
    size = (cameras[0].width, cameras[0].height)
    points, kept, conf, swapped, err = triangulate_views(P, dets, found, size, mcfg, mirror_index(names))
    per_view = ViewResults(
        K=np.stack([c.K for c in cameras]), R=np.stack([c.R for c in cameras]), t=np.stack([c.t for c in cameras]),
        size=size, boxes=np.asarray(boxes, np.float64), detections=dets, found=found, swapped=swapped,
        used=kept, error_px=err,
    )  # fmt: skip
    return ScanKeypoints(
        names=names, points=points, confidence=conf, num_views=kept.sum(0), views=len(cameras),
        views_with_person=int(found.sum()), detector=getattr(detector, "name", "?"), per_view=per_view,
        images=images if keep_images else None,
    )  # fmt: skip


def with_landmarks(scan: Scan, found: ScanKeypoints, where: str = "scan") -> Scan:
    """A copy of ``scan`` whose landmarks are the detected ones (the detector's names; any landmarks
    the scan had are replaced). Fewer than 8 located is a ValueError naming ``where``."""
    lm = np.asarray(found.points, np.float32)
    ok = int(np.isfinite(lm).all(1).sum())
    if ok < 8:
        raise ValueError(f"{where}: only {ok} landmarks located from the renders (need >= 8)")
    lm[~np.isfinite(lm).all(1)] = np.nan
    meta = {**(scan.meta or {}), "landmarks_from": {
        "detector": found.detector, "views": found.views, "views_with_person": found.views_with_person,
        "view_failure_rate": 1 - found.views_with_person / found.views, "located": ok,
        "swapped_views": int(found.per_view.swapped.sum())}}  # fmt: skip
    return replace(scan, landmark_names=list(found.names), landmarks=lm, meta=meta)
