"""Made docs/figures/recovery_mesh_levels.png (recovery_mesh.md "Mesh operators"; 2026-11-25, 6155689).

The mesh hierarchy of the spiral networks (thesis Fig. 4.2 on our template): the reference pose
and the meshes after each down-sampling, front and side. Writes docs/figures/recovery_mesh_levels.png.

    python experiments/figures/mesh_levels_figure.py --out docs/figures/recovery_mesh_levels.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from recovery.mesh.operators import mesh_operators
from recovery.utils.geometry import UPRIGHT_FACING_CAMERA
from recovery.utils.viz import side_view


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="docs/figures/recovery_mesh_levels.png")
    ap.add_argument("--size", type=int, default=260)
    args = ap.parse_args()
    ops = mesh_operators()
    up = UPRIGHT_FACING_CAMERA.numpy()
    pos = ops.reference.astype(np.float64)
    keep = np.arange(len(pos))
    cells = []
    for lvl, faces in enumerate(ops.faces):
        v = pos[keep] @ up.T
        front = side_view([(v, (0.75, 0.78, 0.85))], faces, args.size, yaw_deg=0.0)
        side = side_view([(v, (0.75, 0.78, 0.85))], faces, args.size, yaw_deg=90.0)
        cells.append((f"level {lvl}: {len(keep)} vertices, {len(faces)} faces", front, side))
        if lvl < len(ops.levels):
            keep = keep[ops.levels[lvl].down]
    s = args.size
    sheet = Image.new("RGB", (s * len(cells), 2 * s + 18), "white")
    d = ImageDraw.Draw(sheet)
    for i, (title, front, side) in enumerate(cells):
        sheet.paste(Image.fromarray(front), (i * s, 18))
        sheet.paste(Image.fromarray(side), (i * s, 18 + s))
        d.text((i * s + 4, 3), title, fill="black")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    sheet.save(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
