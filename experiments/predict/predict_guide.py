"""Does each predicted body land on its own person? ``recovery predict`` with and without the detector's
keypoints steering MoveNet's decoding in each person's crop (:meth:`recovery.models.backbones.movenet.
MoveNet.keypoints`, ``guide``), on the same detections.

    python experiments/predict/predict_guide.py [--checkpoint default] [--images out/predict_devset/images]
        [--json docs/figures/predict_guide.json]

For every detected person, COCO's object keypoint similarity (OKS, :func:`recovery.detect.keypoint_similarity`)
between the fitted body's 17 COCO keypoints projected into the image and the detector's own keypoints of
that person (MultiPose's, which each belong to one person): a body on a neighbour has a low OKS. A person
counts as "on someone else" under 0.5 (COCO's loosest threshold of its AP range).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", default="default")
    ap.add_argument("--images", type=Path, default=ROOT / "out/predict_devset/images")
    ap.add_argument("--work", type=Path, default=ROOT / "out/predict_guide")
    ap.add_argument("--json", type=Path, default=ROOT / "docs/figures/predict_guide.json")
    args = ap.parse_args(argv)
    import recovery.predict as rp
    from recovery.detect import _area, keypoint_similarity
    from recovery.models.backbones.movenet import COCO_KEYPOINTS

    plain = rp.predict_crops
    runs: dict[str, dict] = {}
    for mode in ("unguided", "guided"):
        # the same detections; "unguided" drops the detector's keypoints on the way to the network (before 2026-12-06)
        rp.predict_crops = plain if mode == "guided" else (lambda pr, image, crops, k, guides=None: plain(pr, image, crops, k))
        out = args.work / mode
        t0 = time.time()
        rp.predict_people(args.checkpoint, args.images, out)
        doc = json.loads((out / "people.json").read_text())
        names = doc["keypoint_names"]
        ids = [names.index(n) for n in COCO_KEYPOINTS]
        people = []
        for im in doc["images"]:
            for i, p in enumerate(im["people"]):
                det = np.asarray(p["detector_keypoints"], np.float64)
                body = np.concatenate([np.asarray(p["keypoints_2d"], np.float64)[ids], np.ones((17, 1))], 1)
                oks = keypoint_similarity(det, body, _area(np.asarray(p["box"])))
                people.append({"image": im["image"], "person": i, "oks": round(float(oks), 3)})
        oks = np.array([p["oks"] for p in people])
        runs[mode] = {"people": people, "elsewhere": int((oks < 0.5).sum()), "median_oks": float(np.median(oks)),
                      "seconds": round(time.time() - t0, 1)}
        print(f"[guide] {mode}: {len(people)} people, {runs[mode]['elsewhere']} under OKS 0.5, median OKS "
              f"{runs[mode]['median_oks']:.3f}", flush=True)
    rp.predict_crops = plain
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"checkpoint": args.checkpoint, "images": str(args.images), **runs}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
