"""MediaPipe Pose (BlazePose GHUM 3D, "full" model) as a stand-alone 2D pose script.

Used by markerless scan keypoints (:mod:`blsm.pose2d.detectors`, :mod:`blsm.learn.markerless.keypoints`) and
as the reference estimator of ``recovery transfer`` (:mod:`recovery.eval.transfer`). Run as a script
in an environment with ``mediapipe==0.10.9`` (``scripts/setup_reference.sh`` makes one; MediaPipe
pins its own protobuf and OpenCV, so it stays out of the project's environment)::

    python blsm/pose2d/mediapipe_pose.py JOB.json OUT.json

``JOB.json`` is ``{"items": [{"image": PATH, "box": [x0, y0, x1, y1]}, ...]}``. For each item the
image is cropped to the square of side ``CROP_GROWTH`` times the box's longer side around the box's
centre (zero padding outside the image), so that BlazePose sees the one person the box names, and the
33 landmarks are mapped back to image pixels (pixel centres at integer + 0.5, as the project's
convention). ``OUT.json`` gets ``{"reference": "mediapipe-pose 0.10.9 full", "items": [{"landmarks":
[[x, y, visibility], ... 33] or null}, ...]}``; null where BlazePose finds no person.

This file imports neither torch nor the project: only NumPy, Pillow or OpenCV, and MediaPipe.
"""

from __future__ import annotations

import json
import sys

CROP_GROWTH = 1.25  # the crop around a box handed to BlazePose (its detector expects some margin)
NUM_LANDMARKS = 33


def crop_square(image, box, growth=CROP_GROWTH):  # noqa: ANN001, ANN201 (no typing imports needed here)
    """(crop, x0, y0, side): the square crop around ``box``, zero-padded outside the image."""
    import numpy as np

    h, w = image.shape[:2]
    x0, y0, x1, y1 = (float(v) for v in box)
    side = max(x1 - x0, y1 - y0) * growth
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    left, top, n = int(round(cx - side / 2)), int(round(cy - side / 2)), max(int(round(side)), 1)
    out = np.zeros((n, n, 3), np.uint8)
    sx0, sy0, sx1, sy1 = max(left, 0), max(top, 0), min(left + n, w), min(top + n, h)
    if sx1 > sx0 and sy1 > sy0:
        out[sy0 - top:sy1 - top, sx0 - left:sx1 - left] = image[sy0:sy1, sx0:sx1]
    return out, left, top, n


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print("usage: mediapipe_pose.py JOB.json OUT.json", file=sys.stderr)
        return 2
    import mediapipe as mp
    import numpy as np
    from PIL import Image

    job = json.loads(open(argv[0]).read())
    results = []
    cache: dict[str, np.ndarray] = {}
    with mp.solutions.pose.Pose(static_image_mode=True, model_complexity=1, enable_segmentation=False,
                                min_detection_confidence=0.5) as pose:
        for item in job["items"]:
            path = item["image"]
            if path not in cache:
                cache.clear()
                with Image.open(path) as im:
                    cache[path] = np.array(im.convert("RGB"))
            crop, left, top, n = crop_square(cache[path], item["box"])
            res = pose.process(crop)
            if res.pose_landmarks is None:
                results.append({"landmarks": None})
                continue
            lms = [[left + lm.x * n, top + lm.y * n, lm.visibility] for lm in res.pose_landmarks.landmark]
            results.append({"landmarks": lms})
    with open(argv[1], "w") as fh:
        json.dump({"reference": f"mediapipe-pose {mp.__version__} full", "items": results}, fh)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
