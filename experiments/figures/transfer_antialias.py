"""The crops a network sees of the development set's photographs, bilinear sampling alone against
the prefiltered warp (docs/transfer.md, "Crops of large photographs, antialiased").

    python experiments/figures/transfer_antialias.py --real out/transfer_dev \
        --reference out/transfer/check_aa/default_on/reference.json --out docs/figures/transfer_antialias.jpg

Each column: one scored person (the check's box rule, the reference's cached joints), top the crop
as before 2026-12-02, bottom as now; the shrink (source pixels per crop pixel) over each column.
People are taken in order of shrink, largest first.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--real", type=Path, required=True)
    ap.add_argument("--reference", type=Path, required=True, help="a transfer check's reference.json")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--count", type=int, default=6)
    ap.add_argument("--crop", type=int, default=128)
    args = ap.parse_args()
    import torch
    from PIL import Image, ImageDraw

    from recovery.eval import transfer as T
    from recovery.predict import read_image
    from synth.dataset.crops import crop_affine, crop_shrink, warp_to_crop

    people = T.read_boxes(args.real)
    _, _, centre, side, ok = T.reference_boxes(people, T.reference_command(None), args.reference)  # cached: nothing runs
    idx = [int(i) for i in np.flatnonzero(ok)]
    affs = {i: crop_affine(tuple(centre[i]), float(side[i]) * T.CROP_SCALE, args.crop) for i in idx}
    idx = sorted(idx, key=lambda i: -crop_shrink(affs[i]))[: args.count]
    c, pad = args.crop, 16
    sheet = Image.new("RGB", (len(idx) * c, 2 * c + pad), (30, 30, 30))
    draw = ImageDraw.Draw(sheet)
    for n, i in enumerate(idx):
        img = torch.from_numpy(read_image(people[i].image)).permute(2, 0, 1).float() / 255.0
        for row, aa in enumerate((False, True)):
            crop = warp_to_crop(img, affs[i], c, antialias=aa)
            arr = (crop.permute(1, 2, 0).clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
            sheet.paste(Image.fromarray(arr), (n * c, pad + row * c))
        draw.text((n * c + 3, 2), f"shrink {crop_shrink(affs[i]):.1f}", fill=(255, 255, 255))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(args.out, quality=90)
    print(f"wrote {args.out}: {len(idx)} people")


if __name__ == "__main__":
    main()
