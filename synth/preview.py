"""``synth preview``: a contact sheet of a dataset with every overlay on its person.

Each sample gives one row of four tiles: the image with keypoints and skeleton (filled dots for
visible keypoints, hollow for hidden ones in frame) and boxes (visible box solid, whole-body box
dashed), the instance mask over the image, the six parts, and the per-bone labels.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from synth import format as fmt
from synth.shards import read_shard

# Skeleton edges by keypoint name (BLSM joints plus the face points).
EDGES = (
    ("pelvis", "spine_01"), ("spine_01", "spine_02"), ("spine_02", "spine_03"), ("spine_03", "neck"),
    ("neck", "head"), ("head", "head_top"), ("spine_03", "clavicle_l"), ("clavicle_l", "shoulder_l"),
    ("shoulder_l", "elbow_l"), ("elbow_l", "wrist_l"), ("wrist_l", "hand_tip_l"), ("spine_03", "clavicle_r"),
    ("clavicle_r", "shoulder_r"), ("shoulder_r", "elbow_r"), ("elbow_r", "wrist_r"), ("wrist_r", "hand_tip_r"),
    ("pelvis", "hip_l"), ("hip_l", "knee_l"), ("knee_l", "ankle_l"), ("ankle_l", "toe_tip_l"), ("ankle_l", "heel_l"),
    ("pelvis", "hip_r"), ("hip_r", "knee_r"), ("knee_r", "ankle_r"), ("ankle_r", "toe_tip_r"), ("ankle_r", "heel_r"),
    ("nose", "left_eye"), ("nose", "right_eye"), ("left_eye", "left_ear"), ("right_eye", "right_ear"),
)  # fmt: skip
PERSON_COLOURS = ((255, 60, 60), (60, 200, 255), (255, 210, 0), (170, 90, 255), (60, 255, 120), (255, 120, 200))


def _side_colour(name: str, base: tuple[int, int, int]) -> tuple[int, int, int]:
    if name.endswith("_l") or name.startswith("left_"):
        return (0, 220, 0)
    if name.endswith("_r") or name.startswith("right_"):
        return (230, 0, 230)
    return base


def draw_sample(sample: dict, scale: int = 2) -> Image.Image:
    """One row of four tiles for a decoded sample (:func:`synth.format.decode_sample`)."""
    rgb, doc = sample["rgb"], sample["json"]
    h, w = rgb.shape[:2]
    big = (w * scale, h * scale)
    img = Image.fromarray(rgb).resize(big, Image.NEAREST)
    d = ImageDraw.Draw(img)
    names = doc["keypoint_names"]
    for i, p in enumerate(doc["people"]):
        base = PERSON_COLOURS[i % len(PERSON_COLOURS)]
        kp = np.asarray(p["keypoints_2d"]) * scale
        vis, inf = p["visible"], p["in_frame"]
        for a, b in EDGES:
            ia, ib = names.index(a), names.index(b)
            if inf[ia] and inf[ib]:
                d.line([tuple(kp[ia]), tuple(kp[ib])], fill=base, width=1)
        for k, name in enumerate(names):
            if not inf[k]:
                continue
            x, y = kp[k]
            c = _side_colour(name, base)
            r = 2.5
            if vis[k]:
                d.ellipse([x - r, y - r, x + r, y + r], fill=c)
            else:
                d.ellipse([x - r, y - r, x + r, y + r], outline=c)
        if p["box"] is not None:
            d.rectangle([v * scale for v in p["box"]], outline=base)
        bf = [v * scale for v in p["box_full"]]
        for x0, y0, x1, y1 in ((bf[0], bf[1], bf[2], bf[1]), (bf[0], bf[3], bf[2], bf[3]), (bf[0], bf[1], bf[0], bf[3]), (bf[2], bf[1], bf[2], bf[3])):
            n = max(1, int(max(abs(x1 - x0), abs(y1 - y0)) // 6))
            for t in range(0, n, 2):
                d.line([(x0 + (x1 - x0) * t / n, y0 + (y1 - y0) * t / n), (x0 + (x1 - x0) * (t + 1) / n, y0 + (y1 - y0) * (t + 1) / n)], fill=base)
    tiles = [img]
    mask = sample["mask"]
    over = rgb.astype(np.float32).copy()
    for i in range(len(doc["people"])):
        sel = mask == i + 1
        over[sel] = 0.45 * over[sel] + 0.55 * np.array(PERSON_COLOURS[i % len(PERSON_COLOURS)])
    tiles.append(Image.fromarray(over.astype(np.uint8)).resize(big, Image.NEAREST))
    for key, pal in (("parts", fmt.PART_PALETTE), ("bones", fmt.BONE_PALETTE)):
        col = fmt.colorize(sample[key], pal).astype(np.float32)
        blend = np.where(sample[key][..., None] > 0, 0.8 * col + 0.2 * rgb, 0.35 * rgb)
        tiles.append(Image.fromarray(blend.astype(np.uint8)).resize(big, Image.NEAREST))
    row = Image.new("RGB", (big[0] * 4 + 6, big[1]), (255, 255, 255))
    for t, tile in enumerate(tiles):
        row.paste(tile, (t * (big[0] + 2), 0))
    return row


def contact_sheet(dataset: str | Path, out: str | Path, count: int = 8, scale: int = 2) -> Path:
    """Write a PNG with ``count`` samples of ``dataset`` (the first ones, across shards)."""
    dataset, out = Path(dataset), Path(out)
    shards = sorted(dataset.glob("shard-*.tar"))
    if not shards:
        raise ValueError(f"{dataset}: no shards (shard-*.tar) in this folder")
    rows = []
    for sh in shards:
        for key, fields in sorted(read_shard(sh).items()):
            rows.append(draw_sample(fmt.decode_sample(fields, f"{sh}:{key}"), scale))
            if len(rows) >= count:
                break
        if len(rows) >= count:
            break
    sheet = Image.new("RGB", (rows[0].width, sum(r.height + 4 for r in rows)), (255, 255, 255))
    y = 0
    for r in rows:
        sheet.paste(r, (0, y))
        y += r.height + 4
    from blsm.io import atomic_write

    with atomic_write(out) as f:
        sheet.save(f, format="PNG")
    return out
