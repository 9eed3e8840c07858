"""How much the transfer check's scores move when every crop is shifted by less than a pixel
(docs/transfer.md, "Crops of large photographs, antialiased"): the same checkpoint, the same
people and boxes, the crop centres moved by a uniform sub-pixel offset (at most half a source
pixel each way), several draws. A network that reads the person barely moves; the spread of the
draws is a noise of the check that the bootstrap over people does not hold.

    python experiments/transfer/transfer_jitter.py CHECKPOINT --check out/transfer/check_aa/default_on [--draws 8]

``--check`` is a ``recovery transfer`` output folder: its ``reference.json`` is reused (nothing
runs the reference again) and its synthetic images are read from there.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--check", type=Path, required=True)
    ap.add_argument("--real", default=str(ROOT / "out/transfer_dev"))
    ap.add_argument("--synthetic", default=str(ROOT / "out/data/test"))
    ap.add_argument("--draws", type=int, default=8)
    ap.add_argument("--no-antialias", action="store_true")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--fit", type=int, help="the test-time fit's iterations (default: the checkpoint's own)")
    args = ap.parse_args()
    import torch

    from recovery.eval import transfer as T

    torch.set_num_threads(2)
    pr = T.scored_predictor(args.checkpoint, fit=args.fit)  # a checkpoint, or movenet_lightning / movenet_thunder (the ceiling)
    command = T.reference_command(None)
    domains = {"real": T.read_boxes(args.real),
               "synthetic": T.synthetic_people(args.synthetic, args.check / "synthetic_images", 400)}
    out: dict[str, dict] = {}
    rng = np.random.default_rng(0)
    for name, people in domains.items():
        ref, vis, centre, side, ok = T.reference_boxes(people, command, args.check / "reference.json")
        floor = T.mean_pose_floor(ref, vis, centre, side, ok)
        j = vis[ok].sum()
        pck_floor = T.hits(floor[ok], ref[ok], vis[ok], side[ok], 0.1).sum() / j
        scores = []
        for d in range(args.draws + 1):
            shift = np.zeros_like(centre) if d == 0 else rng.uniform(-0.5, 0.5, centre.shape)
            ours, _ = T.predict_joints(pr, people, centre + shift, side, ok, antialias=not args.no_antialias)
            scores.append(float(T.hits(ours[ok], ref[ok], vis[ok], side[ok], 0.1).sum() / j))
        out[name] = {"pck@0.1_unshifted": scores[0], "pck@0.1_shifted": scores[1:], "floor": float(pck_floor),
                     "people": int(ok.sum())}
        s = np.asarray(scores[1:])
        print(f"{name}: {ok.sum()} people, PCK@0.1 unshifted {100 * scores[0]:.1f} %, shifted {100 * s.mean():.1f} % "
              f"(sd {100 * s.std(ddof=1):.1f}, range {100 * s.min():.1f}-{100 * s.max():.1f}), floor {100 * pck_floor:.1f} %",
              flush=True)
    gain = {k: np.asarray(v["pck@0.1_shifted"]) - v["floor"] for k, v in out.items()}
    ratio = gain["real"] / gain["synthetic"]
    out["transfer_ratio_shifted"] = ratio.tolist()
    print(f"transfer ratio over the shifted draws: {ratio.mean():.2f} (sd {ratio.std(ddof=1):.2f}, "
          f"range {ratio.min():.2f} to {ratio.max():.2f})")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
