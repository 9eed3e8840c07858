"""Held-out markerless registrations against their scans, coloured by the error against the true
correspondence (docs/markerless.md, "The hands and feet searched again").

    python experiments/figures/markerless_errors.py --out docs/figures/markerless_errors.png \
        --scans out/register4d/heldout/scans --regs out/reg_heldout/scans_mediapipe_regressor_r48i60 \
        out/reg_heldout/scans_mediapipe_regressor_r96i60h48f --ids s00000_01 s00005_01

Each row: the textured scan, then each registration folder's result (white-blue 0 mm to red 20 mm
and more), from the front and from the side (the scan's own turn about Y taken out).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scans", type=Path, required=True)
    ap.add_argument("--regs", type=Path, nargs="+", required=True)
    ap.add_argument("--ids", nargs="+", required=True)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    import blsm
    from blsm.camera import auto_camera
    from blsm.learn.registration.registrations import load_registration
    from blsm.learn.scans.format import load_scan
    from blsm.render import render_meshes, save_png

    faces = blsm.load().faces.numpy()
    rows = []
    for stem in args.ids:
        s = load_scan(args.scans / f"{stem}.npz")
        turn = float(np.degrees(np.asarray(s.gt_global_orient).reshape(-1)[1]))
        tiles = []
        for folder in args.regs:
            r = load_registration(folder / f"{stem}.npz")
            e = np.linalg.norm(r.vertices - s.gt_points, axis=1) * 1000
            t = np.clip(e / 20.0, 0, 1)[:, None]
            tiles.append((r.vertices, (1 - t) * np.array([0.55, 0.7, 0.95]) + t * np.array([0.95, 0.1, 0.1])))
            print(f"{stem} {folder.name}: {e.mean():.2f} mm", flush=True)
        for az in (0.0, 90.0):
            cam = auto_camera([(s.vertices, s.faces)], 256, 320, azimuth_deg=az + turn)
            row = [render_meshes([(s.vertices, s.faces)], cam, vertex_colors=[s.colors], spp=4)]
            row += [render_meshes([(v, faces)], cam, vertex_colors=[vc], spp=4) for v, vc in tiles]
            rows.append(np.concatenate(row, 1))
    save_png(np.concatenate(rows, 0), args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
