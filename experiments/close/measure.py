"""Close placement measured over a dataset (issue 55): per image, the closest distance between two
people and the deepest interpenetration, both by the exact test (:mod:`blsm.occupancy`) on the
bodies rebuilt from the labels, at every vertex and at dense surface samples.

    python experiments/close/measure.py out/close --out docs/figures/close.json

Per placed pair (``placement.pairs``): ``gap`` = the smallest unsigned distance from a surface
point of one body to the other's surface, 0 where they interpenetrate; ``depth`` = the largest
distance to the other's surface of a point of one inside the other (0 where none is). Points: the
body-mesh vertices and ``--samples`` points uniform on each body's surface. Hair and clothes are not
bodies (the placement keeps their vertices out of the other body too). Also: the arrangements drawn
and placed, the share of images with a contact label, and the seats shared as one bench.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

import numpy as np

from blsm import occupancy
from synth.dataset.format import decode_json
from synth.dataset.shards import read_shard
from synth.validate import MeshRebuilder


def pair_measure(a: tuple, b: tuple, n: int, rng: np.random.Generator) -> tuple[float, float]:
    """(gap, depth) metres between bodies ``a`` and ``b`` ((V, 3) vertices, (F, 3) faces)."""
    gap, depth = np.inf, 0.0
    for (va, fa), (vb, fb) in ((a, b), (b, a)):
        pts = np.concatenate([va, occupancy.surface_points(va, fa, n, rng)])
        s = occupancy.signed_distance(pts, vb, fb)[0]  # exact winding-number sign
        gap = min(gap, float(max(s.min(), 0.0)))
        depth = max(depth, float(-s.min()) if s.min() < 0 else 0.0)
    return gap, depth


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--out", type=Path, help="write the summary JSON here")
    ap.add_argument("--samples", type=int, default=20000, help="surface points per body and pair")
    args = ap.parse_args(argv)
    man = json.loads((args.dataset / "manifest.json").read_text())
    rebuild = MeshRebuilder(args.dataset, man.get("config", {}))
    rng = np.random.default_rng(0)
    gaps, depths, image_depth, image_gap = [], [], [], []
    drawn, placed = Counter(), Counter()
    touching = benches = seated_images = 0
    images = 0
    for name in sorted(man["shards"]):
        for key, fields in sorted(read_shard(args.dataset / name).items()):
            doc = decode_json(fields["json"], f"{name}:{key}")
            images += 1
            bodies = []
            for p in doc["people"]:
                rebuild.mesh(p)
                v = rebuild.last_body  # the body's vertices and faces
                bodies.append(v)
            pl = doc.get("placement") or {}
            drawn[pl.get("arrangement", "none")] += 1
            if pl.get("arrangement") == "seated":
                seated_images += 1
                benches += bool(pl.get("bench"))
            worst, best = 0.0, np.inf
            for pair in pl.get("pairs", []):
                i, j = pair["people"]
                placed[pair["arrangement"]] += 1
                g, d = pair_measure(bodies[i], bodies[j], args.samples, rng)
                gaps.append(g)
                depths.append(d)
                worst, best = max(worst, d), min(best, g)
            image_depth.append(worst)
            image_gap.append(best)
            touching += any(c["vertices"][0] for c in doc.get("contacts") or [])
    mm = lambda x: round(1000.0 * float(x), 2)  # noqa: E731
    summary = {
        "dataset": str(args.dataset), "images": images, "pairs": len(gaps),
        "points": f"every body vertex and {args.samples} surface samples per body and pair",
        "gap_mm": {"median": mm(np.median(gaps)), "p90": mm(np.percentile(gaps, 90)), "max": mm(np.max(gaps))},
        "depth_mm": {"median": mm(np.median(depths)), "p99": mm(np.percentile(depths, 99)), "max": mm(np.max(depths))},
        "images_depth_under_10mm": round(float(np.mean(np.asarray(image_depth) < 0.01)), 4),
        "image_closest_gap_mm_median": mm(np.median(image_gap)),
        "images_with_contact_label": round(touching / max(images, 1), 4),
        "arrangements_drawn": dict(drawn), "pairs_placed": dict(placed),
        "seated_images_on_one_bench": f"{benches}/{seated_images}",
    }  # fmt: skip
    print(json.dumps(summary, indent=1))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(summary, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
