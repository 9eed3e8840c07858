"""``blsm`` command line: ``info``, ``atoms``, ``demo``, ``build-anny``; ``mocap ...``
(:mod:`blsm.mocap.cli`) and the learning commands ``scans``, ``register``, ``learn``, ``train``,
``evaluate``, ``train-smpl`` (:mod:`blsm.learn.cli`).

Every command exits non-zero with a one-line ``blsm: error: ...`` on bad input and writes its
outputs atomically, so an interrupted run leaves no half-written file.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch


def _load(path: str | None):
    import blsm

    return blsm.load(path)


def cmd_info(args: argparse.Namespace) -> int:
    model = _load(args.model)
    meta = model.meta
    rep = meta.get("build_report") or meta.get("train_report") or {}
    n_bodies = rep.get("n_bodies", rep.get("registrations", {}).get("train_rest", "?"))
    print(f"BLSM model: {meta.get('name')} v{meta.get('version')} ({model.meta.get('source', '?')})")
    print(f"  file:        {args.model or 'packaged'}")
    print(f"  mesh:        {model.num_vertices} vertices, {int(model.faces.shape[0])} faces, "
          f"{int(model.uvs.shape[0])} UVs")
    print(f"  bones:       {model.num_joints}")
    for j, name in enumerate(model.bone_names):
        p = model.parents[j]
        n = sum(1 for d in model.dof_table.dofs if d.joint == name)
        print(f"    {j:2d} {name:<11s} parent={model.bone_names[p] if p >= 0 else '-':<11s} atoms={n}")
    print(f"  pose atoms:  {model.num_dofs} (Eq. 6; limits in degrees)")
    for i, d in enumerate(model.dof_table.dofs):
        axis = ("-" if d.axis_sign < 0 else "+") + "xyz"[d.axis]
        lo, hi = (math.degrees(v) for v in d.limits)
        print(f"    {i:2d} {d.name:<22s} axis {axis}  [{lo:7.1f}, {hi:6.1f}]  mirror {d.mirror}"
              f"{' (negated)' if d.mirror_sign < 0 else ''}")
    print(f"  bone coeffs: {model.num_bone_coeffs}", end="")
    if "bone_pca_explained_first3" in rep:
        print(f" (first 3 explain {100 * rep['bone_pca_explained_first3']:.2f} % of bone-length variance"
              f" over {n_bodies} bodies)")
    else:
        print()
    print(f"  shape coeffs: {model.num_shape_coeffs} ({type(model.shape_decoder).__name__})")
    print(f"  keypoints:   {len(model.keypoint_names)}: {', '.join(model.keypoint_names)}")
    print(f"  keypoint sets: {', '.join(f'{k} ({len(v)})' for k, v in model.keypoint_sets.items())}")
    print(f"  parts:       {', '.join(model.part_names)}; per-bone labels in vertex_bones")
    out = model()
    lo, hi = out.vertices[0].min(0).values, out.vertices[0].max(0).values
    print(f"  rest height: {float(hi[1] - lo[1]):.3f} m (Y up, facing +Z)")
    return 0


def _mesh(v: torch.Tensor, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return v.detach().cpu().numpy().astype(np.float64), faces


def _side_azimuth(name: str) -> float:
    if name.endswith("_l") or "_l." in name:
        return 55.0
    if name.endswith("_r") or "_r." in name:
        return -55.0
    return 35.0


def cmd_atoms(args: argparse.Namespace) -> int:
    from blsm import render
    from blsm.camera import auto_camera

    model = _load(args.model)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    faces = model.faces.numpy()
    d = model.num_dofs
    # Fig. 2: every atom at both limits.
    angles = torch.zeros(2 * d, d)
    for i in range(d):
        angles[2 * i, i] = model.dof_limits[i, 0]
        angles[2 * i + 1, i] = model.dof_limits[i, 1]
    with torch.no_grad():
        verts = model(angles=angles).vertices
    items, labels, cams = [], [], []
    w, h = args.tile
    for i, name in enumerate(model.dof_names):
        pair = [_mesh(verts[2 * i], faces), _mesh(verts[2 * i + 1], faces)]
        cam = auto_camera(pair, w, h, azimuth_deg=_side_azimuth(name), elevation_deg=12.0)
        for k in range(2):
            items.append([pair[k]])
            deg = math.degrees(float(model.dof_limits[i, k]))
            labels.append(f"{name} {deg:+.0f}")
            cams.append(cam)
    by_id = {id(item): cam for item, cam in zip(items, cams)}
    atoms_png = render.render_grid(
        items, out_dir / "atoms.png", labels=labels, cols=12, tile_size=(w, h),
        camera_fn=lambda item: by_id[id(item)], spp=args.spp,
    )
    print(f"wrote {atoms_png}")

    # Fig. 8: +-3 sigma along the first bone and shape components. Tiles of one component share a
    # camera so that sizes compare; a value outside the range of the population the model was built
    # from is marked with '*' (linear bases extrapolate poorly there).
    rows, cams8 = [], []
    for kind, n, pop in (
        ("bone", model.num_bone_coeffs, model.population_bone),
        ("shape", model.num_shape_coeffs, model.population_shape),
    ):
        for c in range(min(3, n)):
            group = []
            for sigma in (-3.0, 0.0, 3.0):
                coeff = torch.zeros(1, n)
                coeff[0, c] = sigma
                outside = not float(pop[:, c].min()) <= sigma <= float(pop[:, c].max())
                with torch.no_grad():
                    mesh = _mesh(model(**{kind: coeff}).vertices[0], faces)
                group.append(mesh)
                rows.append((f"{kind}[{c}] {sigma:+.0f} sd{' *' if outside else ''}", [mesh]))
            cam = auto_camera(group, w, h, elevation_deg=8.0)
            cams8 += [cam] * 3
    cam_of = {id(item): cam for (_, item), cam in zip(rows, cams8)}
    comps_png = render.render_grid(
        [r[1] for r in rows], out_dir / "components.png", labels=[r[0] for r in rows], cols=9,
        tile_size=(w, h), camera_fn=lambda item: cam_of[id(item)], spp=args.spp,
    )
    print(f"wrote {comps_png}")
    return 0


# Colours for keypoint overlays: the person's left blue, right red, centre green.
_KP_COLORS = {"l": (40, 90, 230), "r": (220, 40, 40), "c": (20, 160, 60)}


def _kp_side(name: str) -> str:
    if name.startswith("left_") or name.endswith("_l"):
        return "l"
    if name.startswith("right_") or name.endswith("_r"):
        return "r"
    return "c"


def sample_bodies(model, n: int, seed: int) -> dict[str, torch.Tensor]:
    """Random bodies for the demo: bone and shape coefficients of random members of the population
    the model was built from (linear coefficients far outside it give implausible bodies), angles
    uniform in half of each range (which contains 0), yaw uniform in +-45 degrees."""
    g = torch.Generator().manual_seed(seed)
    who = torch.randint(0, model.population_bone.shape[0], (n,), generator=g)
    lo, hi = model.dof_limits[:, 0], model.dof_limits[:, 1]
    u = torch.rand(n, model.num_dofs, generator=g)
    angles = 0.5 * (lo + u * (hi - lo))
    yaw = (torch.rand(n, generator=g) - 0.5) * (math.pi / 2)
    return dict(
        angles=angles,
        bone=model.population_bone[who],
        shape=model.population_shape[who],
        global_orient=torch.stack([torch.zeros(n), yaw, torch.zeros(n)], dim=1),
    )


def cmd_demo(args: argparse.Namespace) -> int:
    from PIL import Image, ImageDraw

    from blsm import render
    from blsm.camera import auto_camera

    model = _load(args.model)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    params = sample_bodies(model, args.n, args.seed)
    with torch.no_grad():
        out = model(**params)
    faces = model.faces.numpy()
    w, h = args.tile
    coco = model.keypoint_sets["coco17"]
    names = model.keypoint_names
    rng = np.random.default_rng(args.seed)
    tiles = []
    for i in range(args.n):
        mesh = _mesh(out.vertices[i], faces)
        cam = auto_camera([mesh], w, h, elevation_deg=10.0)
        color = tuple(float(c) for c in rng.uniform(0.35, 0.85, size=3))
        img = render.render_meshes([mesh], cam, colors=[color], spp=args.spp)
        tile = Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8))
        draw = ImageDraw.Draw(tile)
        uv = cam.project(out.keypoints[i, coco].numpy().astype(np.float64))
        for k, (x, y) in zip(coco, uv):
            col = _KP_COLORS[_kp_side(names[k])]
            # Pixel centres are at integer + 0.5: pixel (i, j) covers [i, i + 1).
            draw.ellipse([x - 2.5, y - 2.5, x + 2.5, y + 2.5], fill=col, outline=(0, 0, 0))
        height = float(out.vertices[i, :, 1].max() - out.vertices[i, :, 1].min())
        draw.text((4, 4), f"#{i} h={height:.2f}m", fill=(0, 0, 0))
        tiles.append(tile)
    cols = 4
    rows = math.ceil(args.n / cols)
    sheet = Image.new("RGB", (cols * w, rows * h), (255, 255, 255))
    for i, tile in enumerate(tiles):
        sheet.paste(tile, ((i % cols) * w, (i // cols) * h))
    png = render.save_png(np.asarray(sheet), out_dir / "contact_sheet.png")
    record = {k: v.tolist() for k, v in params.items()}
    record.update(seed=args.seed, keypoints="coco17 overlay: left blue, right red, centre green")
    from blsm.io import atomic_write

    with atomic_write(out_dir / "params.json", "w") as fh:
        fh.write(json.dumps(record))
    print(f"wrote {png} ({args.n} random bodies, seed {args.seed}) and {out_dir / 'params.json'}")
    return 0


def _tile(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"tile must be WxH, got {text!r}") from exc
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"tile must be positive, got {text!r}")
    return w, h


def cmd_build_anny(args: argparse.Namespace) -> int:
    """``blsm build-anny``: the model (or with ``--rig`` its rig) built from Anny (:mod:`blsm.build_anny`)."""
    from blsm.build_anny import build, rig_of
    from blsm.io import save_model

    data, report = build(n_bodies=args.bodies, seed=args.seed)
    if args.rig:
        data = rig_of(data)
    save_model(data, args.out)
    print(json.dumps(report, indent=1))
    print(f"wrote {args.out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from blsm.leap.cli import add_parser as add_leap
    from blsm.learn.cli import add_parsers as add_learning
    from blsm.learn.cli import command
    from blsm.mocap.cli import add_parser as add_mocap

    p = argparse.ArgumentParser(prog="blsm", description="Bone-Level Skinned Model tools")
    sub = p.add_subparsers(dest="cmd", required=True)
    info = sub.add_parser("info", help="print the model summary")
    info.add_argument("--model", help="model .npz (default: the packaged one)")
    info.set_defaults(func=cmd_info)
    atoms = sub.add_parser("atoms", help="render every pose atom at both limits and +-3 sd components")
    atoms.add_argument("--out", required=True)
    atoms.add_argument("--model")
    atoms.add_argument("--tile", type=_tile, default=(160, 200), help="tile size WxH")
    atoms.add_argument("--spp", type=int, default=8)
    atoms.set_defaults(func=cmd_atoms)
    demo = sub.add_parser("demo", help="contact sheet of random bodies with COCO keypoints")
    demo.add_argument("--out", default="out/demo")
    demo.add_argument("--model")
    demo.add_argument("--n", type=int, default=16)
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--tile", type=_tile, default=(240, 320))
    demo.add_argument("--spp", type=int, default=16)
    demo.set_defaults(func=cmd_demo)
    build = sub.add_parser("build-anny", help="build the model from Anny (needs the 'build' extra)",
                           description="Build the first BLSM from the Anny body model (``blsm build-anny``).")
    build.add_argument("--out", type=Path, required=True, help="model file to write (.npz)")
    build.add_argument("--bodies", type=int, default=600)
    build.add_argument("--seed", type=int, default=0)
    build.add_argument("--rig", action="store_true",
                       help="write only the rig (template, skeleton, weights; no blendshapes): the "
                            "starting point of `blsm train` (blsm/data/blsm_anny_rig.npz)")
    build.set_defaults(func=command("build-anny", cmd_build_anny))
    add_mocap(sub)
    add_leap(sub)  # leap train, leap evaluate (blsm.leap.cli)
    add_learning(sub)  # scans, register, learn, train, evaluate, train-smpl (blsm.learn.cli)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    try:
        return args.func(args)
    except ValueError as exc:
        print(f"blsm: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
