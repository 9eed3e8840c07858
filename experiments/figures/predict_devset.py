"""The README's "photo in, meshes out" figure: ``recovery predict CHECKPOINT`` with no box (the detector
finds the people) on photographs of the transfer development set, each image's overlay (detected boxes |
every person's mesh) stacked into one JPEG.

    python experiments/figures/predict_devset.py [--checkpoint default] [--real out/transfer_dev]
        [--images skimage_astronaut.png gramps_expedition_1897.jpg ...] [--out docs/figures/predict_devset.jpg]

The predictions (``people.json``, meshes, overlays) stay in ``--work`` (default ``out/predict_devset``).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
IMAGES = [
    "gramps_expedition_1897.jpg",
    "gcompris_ireland_musicians.png",
    "skimage_astronaut.png",
    "gimphelp_highlanders.jpg",
    "gcompris_australia_didgeridoo.png",
    "tuxpaint_fireman_a.png",
]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", default="default")
    ap.add_argument("--real", type=Path, default=ROOT / "out/transfer_dev")
    ap.add_argument("--images", nargs="+", default=IMAGES)
    ap.add_argument("--work", type=Path, default=ROOT / "out/predict_devset")
    ap.add_argument("--out", type=Path, default=ROOT / "docs/figures/predict_devset.jpg")
    ap.add_argument("--height", type=int, default=300, help="each overlay's height in the figure, pixels")
    args = ap.parse_args(argv)
    from PIL import Image

    src = args.work / "images"
    shutil.rmtree(src, ignore_errors=True)
    src.mkdir(parents=True)
    for name in args.images:
        path = args.real / "images" / name
        if not path.is_file():
            print(
                f"predict_devset: error: {path}: no such image (python scripts/setup_transfer_devset.py)",
                file=sys.stderr,
            )
            return 2
        shutil.copy(path, src / name)
    pred = args.work / "pred"
    r = subprocess.run(
        [
            str(Path(sys.executable).parent / "recovery"),
            "predict",
            args.checkpoint,
            str(src),
            "--out",
            str(pred),
        ]
    )
    if r.returncode:
        return r.returncode
    rows = []
    for name in args.images:
        im = Image.open(pred / f"{Path(name).stem}_overlay.png").convert("RGB")
        rows.append(im.resize((round(im.width * args.height / im.height), args.height), Image.LANCZOS))
    # two columns of overlays, each overlay itself two panels wide
    cols = 2
    col_w = max(r.width for r in rows)
    n_rows = (len(rows) + cols - 1) // cols
    sheet = Image.new(
        "RGB", (cols * col_w + (cols - 1) * 8, n_rows * args.height + (n_rows - 1) * 8), (255, 255, 255)
    )
    for i, im in enumerate(rows):
        sheet.paste(im, ((i % cols) * (col_w + 8), (i // cols) * (args.height + 8)))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(args.out, quality=88)
    print(f"wrote {args.out} ({sheet.width} x {sheet.height})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
