"""A strip of frames for looking at a retargeted clip: source skeleton beside the BLSM body.

Each column is one frame. The top row draws the source skeleton (every BVH bone, scaled by the
clip's leg-length ratio and placed like the body); the bottom row renders the retargeted mean BLSM
body with Mitsuba with its skeleton drawn over it (left side blue, right side orange, as in the
top row). Both rows of a
column share one camera, which follows the body from a fixed direction (the body's front in the
first frame, turned by 30 degrees, slightly above), so a walk walks and a jump leaves the floor
line (grey).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm.mocap.bvh import read_bvh
from blsm.mocap.library import MotionClip

_SIDE = {"l": (40, 90, 200), "r": (200, 80, 30)}


def _bone_color(name: str) -> tuple[int, int, int]:
    low = name.lower()
    if "_l_" in low or low.endswith("_l") or "left" in low:
        return _SIDE["l"]
    if "_r_" in low or low.endswith("_r") or "right" in low:
        return _SIDE["r"]
    return (60, 60, 60)


def render_preview(
    clip: MotionClip,
    model: Any,
    out_path: str | Path,
    *,
    bvh: str | Path | None = None,
    frames: int = 8,
    tile: tuple[int, int] = (200, 280),
    spp: int = 4,
    azimuth_deg: float = 30.0,
) -> Path:
    """Render the preview strip of a clip (see the module docstring) to ``out_path`` (PNG).

    Args:
        clip: a library clip (:func:`blsm.mocap.library.load_clip`).
        model: the BLSM model (float32).
        bvh: the source BVH; default: the ``source`` path recorded in the clip.
        frames: number of columns, evenly spaced over the clip.
        tile: (width, height) of one image.
    """
    from PIL import Image, ImageDraw, ImageFont

    from blsm.camera import look_at_camera
    from blsm.render import render_meshes, save_png

    src_path = Path(bvh) if bvh is not None else Path(clip.meta.get("source", ""))
    if not src_path.is_file():
        raise ValueError(f"{clip.path}: source BVH {str(src_path)!r} not found; pass it with --bvh")
    motion = read_bvh(src_path, units=clip.meta.get("units", "auto"), fps=clip.fps)
    offset = int(clip.meta.get("first_frame", 0))
    _, src_pos = motion.global_transforms()
    src_pos = src_pos[offset : offset + clip.num_frames]
    if src_pos.shape[0] != clip.num_frames:
        raise ValueError(f"{clip.path}: {src_path} has fewer frames than the clip; wrong source?")
    ratio = float(clip.meta["leg_ratio"])
    root_name = clip.meta["root_source"]
    root_src = src_pos[:, motion.skeleton.index(root_name)]
    heads0 = model.heads[0].double().numpy()
    # transl = ratio * root_src - heads0 + shift (module retarget): recover the constant shift.
    shift = clip.transl[0] + heads0 - ratio * root_src[0]
    placed = ratio * src_pos + shift

    idx = np.unique(np.linspace(0, clip.num_frames - 1, frames).round().astype(int))
    dtype = model.template.dtype
    with torch.no_grad():
        out = model(
            pose=torch.as_tensor(clip.pose[idx], dtype=dtype),
            global_orient=torch.as_tensor(clip.global_orient[idx], dtype=dtype),
            transl=torch.as_tensor(clip.transl[idx], dtype=dtype),
        )
    verts = out.vertices.double().numpy()
    joints = out.joints.double().numpy()
    faces = model.faces.numpy()
    w, h = tile
    sheet = Image.new("RGB", (w * len(idx), 2 * h + 36), "white")
    draw = ImageDraw.Draw(sheet)
    font = ImageFont.load_default()
    draw.text(
        (4, 2),
        f"{clip.name}: source skeleton (top), BLSM body and skeleton (bottom)",
        fill="black",
        font=font,
    )
    # View from the body's front at the clip's first frame, turned by azimuth_deg, slightly above.
    from scipy.spatial.transform import Rotation

    fwd = Rotation.from_rotvec(clip.global_orient[0]).apply([0.0, 0.0, 1.0])
    yaw = np.arctan2(fwd[0], fwd[2]) + np.radians(azimuth_deg)
    view = np.array([np.sin(yaw), 0.25, np.cos(yaw)])
    view /= np.linalg.norm(view)
    parents = motion.skeleton.parents
    for col, t in enumerate(idx):
        target = np.array(
            [
                verts[col, :, 0].mean(),
                0.5 * (verts[col, :, 1].max() + verts[col, :, 1].min()),
                verts[col, :, 2].mean(),
            ]
        )
        cam = look_at_camera(target + 3.6 * view, target, fov_y_deg=32.0, width=w, height=h)
        body = render_meshes([(verts[col], faces)], cam, spp=spp)
        y0 = 20
        top = Image.new("RGB", (w, h), "white")
        td = ImageDraw.Draw(top)
        bottom = Image.fromarray((np.clip(body, 0, 1) * 255 + 0.5).astype(np.uint8))
        bd = ImageDraw.Draw(bottom)
        for d in (td, bd):  # floor line under the body
            f = cam.project(np.array([target + [-1.0, -target[1], 0.0], target + [1.0, -target[1], 0.0]]))
            d.line([tuple(f[0]), tuple(f[1])], fill=(170, 170, 170), width=1)
        uv = cam.project(placed[t])
        for j, p in enumerate(parents):
            if p >= 0:
                td.line([tuple(uv[p]), tuple(uv[j])], fill=_bone_color(motion.skeleton.names[j]), width=2)
        pj = cam.project(joints[col])
        for j, p in enumerate(model.parents):
            if p >= 0:
                bd.line([tuple(pj[p]), tuple(pj[j])], fill=_bone_color(model.bone_names[j]), width=1)
        sheet.paste(top, (col * w, y0))
        sheet.paste(bottom, (col * w, y0 + h))
        draw.text((col * w + 4, y0 + 2 * h + 2), f"frame {t} ({t / clip.fps:.2f} s)", fill="black", font=font)
    return save_png(np.asarray(sheet), out_path)
