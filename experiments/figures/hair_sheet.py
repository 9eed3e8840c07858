"""Made docs/figures/realism_hair.jpg (docs/realism.md, "Hair"; issue 18 part 4, 2026-11-25, 30f6fc6).

Contact sheet of the hair styles of synth.hair: one row per style, front, side and back views.

    python experiments/figures/hair_sheet.py docs/figures/realism_hair.jpg [--subjects out/data/test/subjects]

Each row is one subject with one style (the four styles in order), every joint angle 0, and
rendered with the generator's own renderer under a plain sky. Without ``--subjects`` four people
are drawn from Anny (about 30 s each).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[2])
    ap.add_argument("out", help="PNG to write")
    ap.add_argument("--subjects", help="a dataset's subjects/ folder (default: draw four people from Anny)")
    ap.add_argument("--size", type=int, default=256, help="tile size in pixels")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)

    from PIL import Image

    import blsm
    from blsm.camera import look_at_camera
    from blsm.color import linear_to_srgb, srgb_to_linear
    from synth.hair import STYLES, pose_hair, sample_hair, subject_hair
    from synth.render import PeopleRenderer, RenderMesh
    from synth.subjects import anny_subject, load_subject, pose_subject

    model = blsm.load()
    if a.subjects:
        files = sorted(Path(a.subjects).glob("*.npz"))[: len(STYLES)]
        if len(files) < len(STYLES):
            print(f"{a.subjects}: needs {len(STYLES)} subject files, found {len(files)}", file=sys.stderr)
            return 2
        subjects = [load_subject(f) for f in files]
    else:
        rng = np.random.default_rng(a.seed)
        subjects = [anny_subject(model, f"hair_{i}", rng, texture_size=512) for i in range(len(STYLES))]
    w = a.size
    env = np.full((64, 128, 3), 0.7, np.float32)
    env[:24] = [1.6, 1.8, 2.2]  # a brighter sky above
    renderer = None
    rows = []
    import torch

    from blsm.joint_limits import unconstrained_from_angles

    lim = model.dof_limits  # every joint at angle 0 (clamped into its limits): standing straight
    straight = unconstrained_from_angles(torch.zeros(1, len(lim)).clamp(lim[:, 0], lim[:, 1]), lim)[0].numpy()
    zero = {"pose": straight.astype(np.float32), "global_orient": np.zeros(3, np.float32), "transl": np.zeros(3, np.float32)}
    for i, (s, style) in enumerate(zip(subjects, STYLES)):
        spec = sample_hair(np.random.default_rng([a.seed, i]), {style: 1.0}, s.meta.get("outfit", {}).get("hair", (0.1, 0.06, 0.03)))
        hair = subject_hair(s, model, spec, "rigged")
        p = pose_subject(s, model, zero, "rigged")
        tex = srgb_to_linear(s.texture.astype(np.float32) / 255.0)
        mesh = RenderMesh.build(s.faces, s.uv, s.faces_uv)
        if renderer is None or renderer.meshes[0].key != mesh.key:
            renderer = PeopleRenderer([mesh], [tex.shape[:2]], w, w, env_shape=env.shape[:2], hair=True)
        head = p["joints"][model.bone_names.index("head")] + np.array([0.0, 0.0, 0.0])
        tiles = []
        for deg in (0, 70, 180):
            t = np.radians(deg)
            cam = look_at_camera(head + np.array([0.9 * np.sin(t), 0.12, 0.9 * np.cos(t)]), head, fov_y_deg=30.0, width=w, height=w)
            frame = renderer.render([p["vertices"]], [tex], cam, env, 0.0, 1.0, spp=32, seed=i,
                                    hair=[(pose_hair(hair, p["transforms"]), hair.colours)])  # fmt: skip
            tiles.append(np.round(linear_to_srgb(np.clip(frame.rgb, 0, 1)) * 255).astype(np.uint8))
        rows.append(np.concatenate(tiles, 1))
        print(f"{s.id}: {spec.style}, length {spec.length * 100:.0f} cm", file=sys.stderr)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(rows, 0)).save(a.out)
    print(a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
