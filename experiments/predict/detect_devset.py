"""The person detector (:mod:`recovery.detect`: MoveNet MultiPose in one pass or several) on the transfer
dev set's photographs and their hand-drawn person boxes (``scripts/setup_transfer_devset.py``).

    python experiments/predict/detect_devset.py [--real out/transfer_dev] [--settings single:256 tiles multi]
        [--overlap 0.5] [--threads 1] [--out out/detect_dev] [--full]

A setting is ``PASSES[:SIZE[:MIN_SCORE]]``: ``single`` (one pass on the whole image), ``tiles`` (the
whole image and overlapping tiles, merged) or ``multi`` (``tiles`` with the second look, the default of
``recovery predict``), the input size (default 256) and the person score threshold (default: the
detector's own, 0.25 for one pass, 0.2 for several).

A detection matches a hand box when their IoU is at least 0.5 (greedy, best IoU first, each box and
detection used once). Reported per setting: hand boxes whose longer side is at least ``--min-side``
pixels (100) that a detection matches (found / boxed), all hand boxes found, the detections, those
that match no hand box (a person left unboxed by the dev set's rule, a part or duplicate of a person,
or a false detection: look at the pictures), the median IoU of the matches and the detector's time per
image (median and mean after one warm-up run, with ``--threads`` torch threads; default: torch's).
Writes ``OUT/report.json`` and, per setting, ``OUT/sheet_<setting>.png``: every image with its hand
boxes (white) and detections (coloured, score beside; a detection that matches no box has a red
label); with ``--full`` also ``OUT/<setting>/<image>.png``, each photograph at its own size.
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


def draw(image: np.ndarray, boxes: list[np.ndarray], dets, matched: set[int],
         width: int | None = 640) -> np.ndarray:
    """The image (scaled to ``width``, or as it is) with the hand boxes (white) and the detections
    (coloured boxes, keypoints scoring above 0.3, the score beside; red when the detection matches no
    box)."""
    from PIL import Image, ImageDraw

    from recovery.utils.viz import PERSON_COLORS

    im = Image.fromarray(image)
    s = width / im.width if width else 1.0
    im = im.resize((round(im.width * s), max(1, round(im.height * s))))
    d = ImageDraw.Draw(im)
    for b in boxes:
        d.rectangle([float(v) * s for v in b], outline=(255, 255, 255), width=1)
    for k, det in enumerate(dets):
        col = tuple(int(c * 255) for c in PERSON_COLORS[k % len(PERSON_COLORS)])
        d.rectangle([float(v) * s for v in det.box], outline=col, width=2)
        label = (255, 40, 40) if k not in matched else col
        d.text((det.box[0] * s + 3, det.box[1] * s + 2), f"{k}:{det.score:.2f}", fill=label)
        for x, y, c in det.keypoints:
            if c > 0.3:
                d.ellipse([x * s - 2, y * s - 2, x * s + 2, y * s + 2], fill=col)
    return np.asarray(im)


def parse_setting(text: str) -> tuple[str, int, float | None]:
    """``PASSES[:SIZE[:MIN_SCORE]]`` -> (passes, size, min_score or None)."""
    parts = text.split(":")
    if not 1 <= len(parts) <= 3:
        raise SystemExit(f"detect_devset: a setting is PASSES[:SIZE[:MIN_SCORE]], got {text!r}")
    size = int(parts[1]) if len(parts) > 1 and parts[1] else 256
    return parts[0], size, float(parts[2]) if len(parts) > 2 else None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", type=Path, default=ROOT / "out/transfer_dev")
    ap.add_argument("--settings", nargs="+", default=["single:256", "tiles", "multi"],
                    help="PASSES[:SIZE[:MIN_SCORE]] each (PASSES: single, tiles, multi)")
    ap.add_argument("--overlap", type=float, default=None,
                    help="the tiles' overlap (default: the detector's)")
    ap.add_argument("--min-side", type=float, default=100.0)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    ap.add_argument("--out", type=Path, default=ROOT / "out/detect_dev")
    ap.add_argument("--full", action="store_true", help="also each photograph at its own size")
    args = ap.parse_args()
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    from PIL import Image

    from recovery.detect import MIN_SCORE, MULTI_MIN_SCORE, TILE_OVERLAP, MultiPassDetector, PersonDetector
    from recovery.models.backbones.movenet import build_movenet
    from recovery.models.movenet_multipose import build_multipose
    from recovery.predict import read_image

    boxes_all = json.loads((args.real / "boxes.json").read_text())
    names = sorted(boxes_all)
    images = {n: read_image(args.real / "images" / n) for n in names}
    net, look_net = build_multipose(), build_movenet("movenet_lightning").eval()
    overlap = TILE_OVERLAP if args.overlap is None else args.overlap
    args.out.mkdir(parents=True, exist_ok=True)
    report = {"min_side": args.min_side, "threads": torch.get_num_threads(), "overlap": overlap,
              "settings": {}}
    table = []
    for setting in args.settings:
        passes, size, min_score = parse_setting(setting)
        if passes == "single":
            det = PersonDetector(size=size, min_score=MIN_SCORE if min_score is None else min_score, net=net)
        elif passes in ("tiles", "multi"):
            det = MultiPassDetector(size=size, min_score=MULTI_MIN_SCORE if min_score is None else min_score,
                                    look=passes == "multi", overlap=overlap, net=net, look_net=look_net)
        else:
            raise SystemExit(f"detect_devset: unknown passes {passes!r} (single, tiles, multi)")
        tag = f"{passes}_{size}_{det.min_score:g}"
        det(images[names[0]])  # warm-up
        rows, tiles, times, ious = [], [], [], []
        for n in names:
            t0 = time.perf_counter()
            found = det(images[n])
            times.append(time.perf_counter() - t0)
            hand = [np.asarray(b, float) for b in boxes_all[n]]
            m = match(hand, [d.box for d in found])
            ious += [iou(hand[i], found[j].box) for i, j in m.items()]
            big = [i for i, b in enumerate(hand) if max(b[2] - b[0], b[3] - b[1]) >= args.min_side]
            unmatched = [{"index": j, "box": [round(float(v), 1) for v in d.box], "score": round(d.score, 3)}
                         for j, d in enumerate(found) if j not in m.values()]
            rows.append({"image": n, "size": list(images[n].shape[1::-1]), "boxed": len(hand),
                         "boxed_big": len(big), "found": len(m), "found_big": sum(i in m for i in big),
                         "detections": len(found), "unmatched": unmatched,
                         "missed_big": [boxes_all[n][i] for i in big if i not in m],
                         "seconds": round(times[-1], 4)})
            tiles.append(draw(images[n], hand, found, set(m.values())))
            if args.full:
                (args.out / tag).mkdir(exist_ok=True)
                full = draw(images[n], hand, found, set(m.values()), width=None)
                Image.fromarray(full).save(args.out / tag / f"{Path(n).stem}.png")
        tot = {k: sum(r[k] for r in rows) for k in ("boxed", "boxed_big", "found", "found_big", "detections")}
        tot["unmatched"] = sum(len(r["unmatched"]) for r in rows)
        tot["median_iou"] = round(float(np.median(ious)), 3) if ious else None
        tot["median_seconds"] = round(float(np.median(times)), 3)
        tot["mean_seconds"] = round(float(np.mean(times)), 3)
        report["settings"][tag] = {"passes": passes, "size": size, "min_score": det.min_score, "total": tot,
                                   "images": rows}
        table.append(f"| {passes} | {size} | {det.min_score:g} | {tot['found_big']}/{tot['boxed_big']} | "
                     f"{tot['found']}/{tot['boxed']} | {tot['detections']} | {tot['unmatched']} | "
                     f"{tot['median_iou']} | {tot['median_seconds']:.2f} | {tot['mean_seconds']:.2f} |")
        print(f"{tag}: found {tot['found_big']}/{tot['boxed_big']} boxed people >= {args.min_side:g} px, "
              f"{tot['found']}/{tot['boxed']} of all; {tot['detections']} detections, "
              f"{tot['unmatched']} match no box; median IoU {tot['median_iou']}; "
              f"{tot['median_seconds'] * 1000:.0f} ms an image (median; mean "
              f"{tot['mean_seconds'] * 1000:.0f}, {torch.get_num_threads()} threads)")
        for r in rows:
            print(f"  {r['image']}: {r['found_big']}/{r['boxed_big']} (all {r['found']}/{r['boxed']}), "
                  f"{r['detections']} detections, unmatched {r['unmatched']}")
        cols = 3
        hmax = max(t.shape[0] for t in tiles)
        padded = [np.pad(t, ((0, hmax - t.shape[0]), (0, 0), (0, 0))) for t in tiles]
        padded += [np.zeros_like(padded[0])] * (-len(padded) % cols)
        rows_img = [np.concatenate(padded[i:i + cols], 1) for i in range(0, len(padded), cols)]
        Image.fromarray(np.concatenate(rows_img, 0)).save(args.out / f"sheet_{tag}.png")
    (args.out / "report.json").write_text(json.dumps(report, indent=1))
    print("| passes | size | min score | found >= min side | found, all | detections | match no box "
          "| median IoU | s/image (median) | s/image (mean) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(table))
    print(f"wrote {args.out}/report.json and sheet_<setting>.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
