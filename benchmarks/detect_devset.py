"""The person detector (:mod:`recovery.detect`, MoveNet MultiPose) on the transfer dev set's photographs
and their hand-drawn person boxes (``scripts/setup_transfer_devset.py``).

    python benchmarks/detect_devset.py [--real out/transfer_dev] [--sizes 256 384] [--threads 1]
        [--out out/detect_dev]

For each input size: a detection matches a hand box when their IoU is at least 0.5 (greedy, best IoU
first, each box and detection used once). Reported: hand boxes whose longer side is at least
``--min-side`` pixels (100) that a detection matches (found / boxed), all hand boxes found, detections
that match no hand box (a person left unboxed by the dev set's rule, a duplicate, or a false
detection: look at the sheets), and the detector's time per image (median after one warm-up run, with
``--threads`` torch threads; default: torch's). Writes ``OUT/report.json`` and, per size,
``OUT/sheet_<size>.png``: every image with its hand boxes (white) and detections (coloured, score beside).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """IoU of two ``x0, y0, x1, y1`` boxes."""
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def match(boxes: list[np.ndarray], dets: list[np.ndarray], thr: float = 0.5) -> dict[int, int]:
    """Greedy one-to-one matching, best IoU first: hand box index -> detection index."""
    pairs = sorted(((iou(b, d), i, j) for i, b in enumerate(boxes) for j, d in enumerate(dets)), reverse=True)
    out, used = {}, set()
    for v, i, j in pairs:
        if v < thr:
            break
        if i not in out and j not in used:
            out[i] = j
            used.add(j)
    return out


def draw(image: np.ndarray, boxes: list[np.ndarray], dets, width: int = 640) -> np.ndarray:
    from PIL import Image, ImageDraw

    from recovery.utils.viz import PERSON_COLORS

    im = Image.fromarray(image)
    s = width / im.width
    im = im.resize((width, max(1, round(im.height * s))))
    d = ImageDraw.Draw(im)
    for b in boxes:
        d.rectangle([float(v) * s for v in b], outline=(255, 255, 255), width=1)
    for k, det in enumerate(dets):
        col = tuple(int(c * 255) for c in PERSON_COLORS[k % len(PERSON_COLORS)])
        d.rectangle([float(v) * s for v in det.box], outline=col, width=2)
        d.text((det.box[0] * s + 3, det.box[1] * s + 2), f"{det.score:.2f}", fill=col)
        for x, y, c in det.keypoints:
            if c > 0.3:
                d.ellipse([x * s - 2, y * s - 2, x * s + 2, y * s + 2], fill=col)
    return np.asarray(im)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", type=Path, default=ROOT / "out/transfer_dev")
    ap.add_argument("--sizes", type=int, nargs="+", default=[256])
    ap.add_argument("--min-side", type=float, default=100.0)
    ap.add_argument("--min-score", type=float, default=None, help="default: recovery.detect.MIN_SCORE")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    ap.add_argument("--out", type=Path, default=ROOT / "out/detect_dev")
    args = ap.parse_args()
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    from PIL import Image

    from recovery.detect import MIN_SCORE, PersonDetector
    from recovery.models.movenet_multipose import build_multipose
    from recovery.predict import read_image

    boxes_all = json.loads((args.real / "boxes.json").read_text())
    names = sorted(boxes_all)
    images = {n: read_image(args.real / "images" / n) for n in names}
    net = build_multipose()
    min_score = MIN_SCORE if args.min_score is None else args.min_score
    args.out.mkdir(parents=True, exist_ok=True)
    report = {"min_score": min_score, "min_side": args.min_side, "threads": torch.get_num_threads(),
              "sizes": {}}
    for size in args.sizes:
        det = PersonDetector(size=size, min_score=min_score, net=net)
        det(images[names[0]])  # warm-up
        rows, tiles, times = [], [], []
        for n in names:
            t0 = time.perf_counter()
            found = det(images[n])
            times.append(time.perf_counter() - t0)
            hand = [np.asarray(b, float) for b in boxes_all[n]]
            m = match(hand, [d.box for d in found])
            big = [i for i, b in enumerate(hand) if max(b[2] - b[0], b[3] - b[1]) >= args.min_side]
            unmatched = [{"box": [round(float(v), 1) for v in d.box], "score": round(d.score, 3)}
                         for j, d in enumerate(found) if j not in m.values()]
            rows.append({"image": n, "size": list(images[n].shape[1::-1]), "boxed": len(hand),
                         "boxed_big": len(big), "found": len(m), "found_big": sum(i in m for i in big),
                         "detections": len(found), "unmatched": unmatched,
                         "missed_big": [boxes_all[n][i] for i in big if i not in m],
                         "seconds": round(times[-1], 4)})
            tiles.append(draw(images[n], hand, found))
        tot = {k: sum(r[k] for r in rows) for k in ("boxed", "boxed_big", "found", "found_big", "detections")}
        tot["unmatched"] = sum(len(r["unmatched"]) for r in rows)
        tot["median_seconds"] = float(np.median(times))
        report["sizes"][str(size)] = {"total": tot, "images": rows}
        print(f"size {size}: found {tot['found_big']}/{tot['boxed_big']} boxed people "
              f">= {args.min_side:g} px, "
              f"{tot['found']}/{tot['boxed']} of all; {tot['detections']} detections, "
              f"{tot['unmatched']} match no box; {tot['median_seconds'] * 1000:.0f} ms an image "
              f"(median, {torch.get_num_threads()} threads)")
        for r in rows:
            print(f"  {r['image']}: {r['found_big']}/{r['boxed_big']} (all {r['found']}/{r['boxed']}), "
                  f"{r['detections']} detections, unmatched {r['unmatched']}")
        cols = 3
        hmax = max(t.shape[0] for t in tiles)
        padded = [np.pad(t, ((0, hmax - t.shape[0]), (0, 0), (0, 0))) for t in tiles]
        padded += [np.zeros_like(padded[0])] * (-len(padded) % cols)
        rows_img = [np.concatenate(padded[i:i + cols], 1) for i in range(0, len(padded), cols)]
        sheet = np.concatenate(rows_img, 0)
        Image.fromarray(sheet).save(args.out / f"sheet_{size}.png")
    (args.out / "report.json").write_text(json.dumps(report, indent=1))
    print(f"wrote {args.out}/report.json and sheet_<size>.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
