"""A contact sheet of a close-placement dataset with its contact labels drawn (issue 55): each image
upscaled, and the contact vertices of every pair (``contacts``) projected onto it, one colour per
person (the bodies rebuilt from the labels, as ``synth validate`` does).

    python experiments/close/figure.py out/close --out docs/figures/close_contacts.jpg --count 12
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from blsm.camera import Camera
from synth.dataset.format import decode_sample
from synth.dataset.shards import read_shard
from synth.validate import MeshRebuilder

COLOURS = [(255, 40, 40), (40, 120, 255), (40, 220, 60), (255, 200, 0)]


def draw(sample: dict, rebuild: MeshRebuilder, scale: int) -> Image.Image:
    doc = sample["json"]
    w, h = doc["image"]["width"], doc["image"]["height"]
    img = Image.fromarray(sample["rgb"]).resize((w * scale, h * scale), Image.NEAREST)
    d = ImageDraw.Draw(img)
    cam = Camera(K=np.array(doc["camera"]["K"]), R=np.array(doc["camera"]["R"]), t=np.array(doc["camera"]["t"]), width=w, height=h)
    bodies = []
    for p in doc["people"]:
        rebuild.mesh(p)
        bodies.append(rebuild.last_body[0])
    for c in doc.get("contacts") or []:
        for side, who in enumerate(c["people"]):
            idx = np.asarray(c["vertices"][side], np.int64)
            if not idx.size:
                continue
            uv = cam.project(bodies[who][idx]) * scale
            for u, v in uv:
                d.ellipse([float(u) - 1.5, float(v) - 1.5, float(u) + 1.5, float(v) + 1.5], fill=COLOURS[who % len(COLOURS)])
    pl = doc.get("placement") or {}
    label = f"{doc['index']}: {pl.get('arrangement', '')}" + (" bench" if pl.get("bench") else "")
    d.rectangle([0, 0, 8 * len(label) + 6, 14], fill=(0, 0, 0))
    d.text((3, 1), label, fill=(255, 255, 255))
    return img


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--count", type=int, default=12)
    ap.add_argument("--scale", type=int, default=2)
    ap.add_argument("--columns", type=int, default=4)
    args = ap.parse_args(argv)
    man = json.loads((args.dataset / "manifest.json").read_text())
    rebuild = MeshRebuilder(args.dataset, man.get("config", {}))
    tiles = []
    for name in sorted(man["shards"]):
        for _, fields in sorted(read_shard(args.dataset / name).items()):
            tiles.append(draw(decode_sample(fields), rebuild, args.scale))
            if len(tiles) == args.count:
                break
        if len(tiles) == args.count:
            break
    tw, th = tiles[0].size
    rows = (len(tiles) + args.columns - 1) // args.columns
    sheet = Image.new("RGB", (tw * args.columns, th * rows))
    for k, t in enumerate(tiles):
        sheet.paste(t, ((k % args.columns) * tw, (k // args.columns) * th))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if args.out.suffix.lower() in (".jpg", ".jpeg"):
        sheet.save(args.out, quality=88)
    else:
        sheet.save(args.out)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
