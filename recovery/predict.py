"""``recovery predict CHECKPOINT IMAGE [--box X0 Y0 X1 Y1] [--focal F] --out DIR``: one person from any image.

The crop is a square around the box's centre of side 1.2 times its longer side (SPIN), or, without a
box, the whole image padded to a square. An arbitrary photo has unknown intrinsics: the camera is
taken as a pinhole with focal length ``--focal`` pixels (default: the image's longer side, about a
53-degree field of view) and the principal point at the image centre; ``K_crop = A K`` with ``A``
the crop's affine map (pixel centres at integer + 0.5). The network predicts the body in that
camera's frame (OpenCV: x right, y down, z forward; metres).

Writes ``DIR/params.json`` (for HMR-BLSM the BLSM parameters: ``pose`` x of Eq. 6, ``angles``
radians, ``bone``, ``shape``, ``global_orient`` axis-angle in the camera frame; for either network
``transl`` the pelvis in the camera frame, the weak-perspective ``cam``, ``keypoints_3d_cam``, ``K``
and ``K_crop``, the box), ``DIR/mesh.obj`` (the mesh in the camera frame, metres) and
``DIR/overlay.png`` (the image, the mesh over it, its parts).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm.io import atomic_write
from recovery.predictor import load_predictor
from recovery.utils.viz import face_parts, overlay, parts_overlay
from synth.data import crop_affine, warp_to_crop


def read_image(path: str | Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an image file; a ValueError names the file when it cannot be read."""
    from PIL import Image, UnidentifiedImageError
    from PIL.Image import DecompressionBombError

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such image")
    try:
        with Image.open(path) as im:
            return np.array(im.convert("RGB"))  # writable: torch.from_numpy warns on a read-only array
    except (UnidentifiedImageError, OSError, DecompressionBombError) as exc:  # bomb: > 179 Mpixels claimed
        raise ValueError(f"{path}: not a readable image ({exc})") from None


def predict(checkpoint: str | Path, image_path: str | Path, out: str | Path, box: tuple[float, ...] | None = None,
            focal: float | None = None, flip: bool = False) -> dict[str, Any]:
    """Predict one person (module docstring); returns the parameters written to ``params.json``.
    ``flip``: HMR-BLSM with flip test-time augmentation (:func:`recovery.models.hmr.flip_average`)."""
    image = read_image(image_path)
    h, w = image.shape[:2]
    if box is not None:
        x0, y0, x1, y1 = box
        if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
            raise ValueError(f"--box {list(box)} is not inside the {w} x {h} image {image_path}")
        centre, side = ((x0 + x1) / 2, (y0 + y1) / 2), max(x1 - x0, y1 - y0) * 1.2
    else:
        centre, side = (w / 2, h / 2), float(max(w, h))
    if focal is not None and focal <= 0:
        raise ValueError(f"--focal must be positive, got {focal}")
    f = float(focal or max(w, h))
    k = np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    pr = load_predictor(checkpoint).use_flip(flip)
    crop = pr.crop
    a = crop_affine(centre, side, crop)
    img = warp_to_crop(torch.from_numpy(image).permute(2, 0, 1).float() / 255.0, a, crop)
    k_crop = torch.tensor(a @ k, dtype=torch.float32)
    res = pr(img[None], k_crop[None])
    from kornia.geometry.conversions import rotation_matrix_to_axis_angle

    from blsm.joint_limits import angles_from_unconstrained

    verts = (res.vertices[0] + res.transl[0]).numpy()
    params: dict[str, Any] = {
        "image": str(image_path), "checkpoint": str(pr.path), "task": pr.task, "box": list(box) if box else None,
        "crop": {"center": list(centre), "side": side, "size": crop},
        "K": k.tolist(), "K_crop": k_crop.tolist(),
    }
    if res.params is not None:
        pred = res.params
        params.update(pose=pred.pose[0].tolist(), angles=angles_from_unconstrained(pred.pose, pr.body.dof_limits)[0].tolist(),
                      bone=pred.bone[0].tolist(), shape=pred.shape[0].tolist(),
                      global_orient=rotation_matrix_to_axis_angle(pred.orient)[0].tolist(), cam=pred.cam[0].tolist())
    params.update({
        "transl": res.transl[0].tolist(),
        "keypoint_names": list(pr.body.keypoint_names),
        "keypoints_3d_cam": (res.keypoints_3d[0] + res.transl[0]).tolist(),
        "conventions": "OpenCV camera (x right, y down, z forward), metres, radians; pixel centres at integer + 0.5",
    })
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    faces = pr.body.faces.numpy()
    with atomic_write(out / "params.json", "w") as fh:
        fh.write(json.dumps(params, indent=1))
    with atomic_write(out / "mesh.obj", "w") as fh:
        fh.write(f"# recovery predict: {image_path}; camera frame (OpenCV), metres\n")
        fh.write("".join(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in verts))
        fh.write("".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
    flabels = face_parts(faces, pr.body.vertex_parts.numpy())
    panel = np.concatenate([image, overlay(image, verts, faces, k), parts_overlay(image, verts, faces, k, flabels)], axis=1)
    from PIL import Image

    tmp = out / ".overlay.png.tmp.png"
    Image.fromarray(panel).save(tmp)
    tmp.replace(out / "overlay.png")
    return params
