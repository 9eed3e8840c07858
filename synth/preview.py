"""``synth preview``: a contact sheet of a dataset with every overlay on its person, and for sequence
datasets (docs/video.md) an animation and a contact sheet of one sequence's frames.

Each sample gives one row of four tiles: the image with keypoints and skeleton (filled dots for
visible keypoints, hollow for hidden ones in frame) and boxes (visible box solid, whole-body box
dashed), the instance mask over the image, the six parts, and the per-bone labels.

:func:`sequence_video` writes a sequence's frames in order, each the first of those tiles with the
frame number, the time and the camera path's kind in its top-left corner, as an animated GIF or an
animated PNG (APNG) at the dataset's frame rate; :func:`sequence_sheet` writes evenly spaced frames
of a sequence as one PNG.
"""

from __future__ import annotations

import json
import tarfile
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from synth.dataset import format as fmt
from synth.dataset.shards import MANIFEST, read_shard, sample_key, shard_name

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


def draw_frame(sample: dict, scale: int = 2) -> Image.Image:
    """The image of a decoded sample (:func:`synth.dataset.format.decode_sample`; ``rgb`` and ``json`` are
    enough), enlarged ``scale`` times, with every person's keypoints, skeleton and boxes."""
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
        if p.get("box_full") is None:
            continue
        bf = [v * scale for v in p["box_full"]]
        for x0, y0, x1, y1 in ((bf[0], bf[1], bf[2], bf[1]), (bf[0], bf[3], bf[2], bf[3]), (bf[0], bf[1], bf[0], bf[3]), (bf[2], bf[1], bf[2], bf[3])):
            n = max(1, int(max(abs(x1 - x0), abs(y1 - y0)) // 6))
            for t in range(0, n, 2):
                d.line([(x0 + (x1 - x0) * t / n, y0 + (y1 - y0) * t / n), (x0 + (x1 - x0) * (t + 1) / n, y0 + (y1 - y0) * (t + 1) / n)], fill=base)
    return img


def draw_sample(sample: dict, scale: int = 2) -> Image.Image:
    """One row of four tiles for a decoded sample (:func:`synth.dataset.format.decode_sample`)."""
    rgb, doc = sample["rgb"], sample["json"]
    h, w = rgb.shape[:2]
    big = (w * scale, h * scale)
    tiles = [draw_frame(sample, scale)]
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


def _first_json(dataset: Path, shards: list[Path]) -> dict[str, Any]:
    """The labels of the first sample of the first shard (read member by member, not the whole shard)."""
    try:
        with tarfile.open(shards[0], mode="r:") as tar:
            for m in tar:
                if m.isfile() and m.name.endswith(".json"):
                    data = tar.extractfile(m)
                    if data is not None:
                        return fmt.decode_json(data.read(), f"{shards[0]}:{m.name}")
    except (OSError, tarfile.TarError) as exc:
        raise ValueError(f"{shards[0]}: not a readable shard ({exc})") from None
    raise ValueError(f"{dataset}: the dataset holds no samples")


def read_sequence(
    dataset: str | Path, sequence: int, fields: tuple[str, ...] = ("rgb.png", "json")
) -> list[dict]:
    """The frames of sequence ``sequence`` of a sequence dataset, decoded, in order of ``frame``.

    The frames are samples ``s T .. s T + T - 1`` (docs/video.md); with the manifest's ``shard_size``
    only the shards holding them are read, and of those only the ``fields`` members of the frames.

    Raises:
        ValueError: one line naming the dataset: no shards, not a sequence dataset (its samples have
            no ``sequence``), no such sequence, or a frame missing or labelled with another sequence.
    """
    dataset = Path(dataset)
    shards = sorted(dataset.glob("shard-*.tar"))
    if not shards:
        raise ValueError(f"{dataset}: no shards (shard-*.tar) in this folder")
    first = _first_json(dataset, shards)
    if "sequence" not in first or "frames" not in first:
        raise ValueError(f"{dataset}: not a sequence dataset (its samples have no 'sequence' label)")
    frames = int(first["frames"])
    man: dict[str, Any] = {}
    if (dataset / MANIFEST).is_file():
        try:
            man = json.loads((dataset / MANIFEST).read_text())
        except (OSError, ValueError):
            man = {}
    total = man.get("num_samples")
    count = int(total) // frames if isinstance(total, int) else None
    if (
        isinstance(sequence, bool)
        or not isinstance(sequence, (int, np.integer))
        or sequence < 0
        or (count is not None and sequence >= count)
    ):
        held = f" (it holds sequences 0 .. {count - 1})" if count else ""
        raise ValueError(f"{dataset}: no sequence {sequence}{held}")
    wanted = {sample_key(sequence * frames + f): f for f in range(frames)}
    size = man.get("shard_size")
    if isinstance(size, int) and size > 0:
        first_shard, last_shard = sequence * frames // size, ((sequence + 1) * frames - 1) // size
        names = {shard_name(i) for i in range(first_shard, last_shard + 1)}
        shards = [sh for sh in shards if sh.name in names] or shards
    found: dict[str, dict[str, bytes]] = {}
    for sh in shards:
        try:
            with tarfile.open(sh, mode="r:") as tar:
                for m in tar:
                    key, _, name = m.name.partition(".")
                    if m.isfile() and key in wanted and name in fields:
                        data = tar.extractfile(m)
                        if data is not None:
                            found.setdefault(key, {})[name] = data.read()
        except (OSError, tarfile.TarError) as exc:
            raise ValueError(f"{sh}: not a readable shard ({exc})") from None
    missing = [f for k, f in wanted.items() if len(found.get(k, {})) < len(fields)]
    if len(missing) == frames:
        raise ValueError(f"{dataset}: no sequence {sequence}")
    if missing:
        raise ValueError(
            f"{dataset}: sequence {sequence} lacks frames {missing} (or some of their {list(fields)})"
        )
    out = []
    for key, f in sorted(wanted.items(), key=lambda kv: kv[1]):
        sample = fmt.decode_sample(found[key], f"{dataset}:{key}")
        doc = sample.get("json", {})
        if doc.get("sequence") != sequence or doc.get("frame") != f:
            raise ValueError(
                f"{dataset}: sample {key} is labelled sequence {doc.get('sequence')} frame "
                f"{doc.get('frame')}, expected sequence {sequence} frame {f}"
            )
        out.append(sample)
    return out


def _caption(img: Image.Image, lines: list[str]) -> Image.Image:
    """Draw text lines on a dark box in the top-left corner (in place; returns ``img``)."""
    d = ImageDraw.Draw(img)
    width = max(d.textlength(t) for t in lines)
    d.rectangle([0, 0, width + 6, 12 * len(lines) + 4], fill=(0, 0, 0))
    for i, t in enumerate(lines):
        d.text((3, 2 + 12 * i), t, fill=(255, 255, 255))
    return img


def _frame_image(sample: dict, scale: int) -> Image.Image:
    doc = sample["json"]
    path = (doc.get("camera") or {}).get("path") or {}
    time = float(doc.get("time", doc["frame"] / doc["fps"]))
    lines = [f"frame {doc['frame']}/{doc['frames'] - 1}  t {time:.3f} s", f"camera {path.get('kind', '?')}"]
    return _caption(draw_frame(sample, scale), lines)


def sequence_video(dataset: str | Path, sequence: int, out: str | Path, scale: int = 1) -> Path:
    """Write sequence ``sequence`` of a sequence dataset as an animation at its frame rate.

    Every frame is :func:`draw_frame` (keypoints, skeleton, boxes) with the frame number, its time in
    seconds and the camera path's kind in the top-left corner. ``out``'s suffix picks the format:
    ``.gif`` (GIF stores frame durations in 1/100 s, so 30 fps plays as 1/0.03 = 33.3 fps; browsers
    slow down frames under 0.02 s) or ``.png`` (animated PNG, exact durations in milliseconds).
    Both loop forever.

    Raises:
        ValueError: one line naming the dataset or the output (see :func:`read_sequence`).
    """
    out = Path(out)
    kind = {".gif": "GIF", ".png": "PNG"}.get(out.suffix.lower())
    if kind is None:
        raise ValueError(f"{out}: the video's suffix must be .gif or .png, got {out.suffix or 'none'!r}")
    samples = read_sequence(dataset, sequence)
    fps = float(samples[0]["json"]["fps"])
    if not fps > 0:
        raise ValueError(f"{dataset}: sequence {sequence} has fps {fps}")
    frames = [_frame_image(s, scale) for s in samples]
    duration = 1000.0 / fps  # milliseconds per frame
    from blsm.io import atomic_write

    with atomic_write(out) as fh:
        if kind == "GIF":
            frames[0].save(
                fh, format="GIF", save_all=True, append_images=frames[1:], duration=round(duration), loop=0
            )
        else:
            frames[0].save(
                fh,
                format="PNG",
                save_all=True,
                append_images=frames[1:],
                duration=duration,
                loop=0,
                default_image=False,
            )
    return out


def sequence_sheet(
    dataset: str | Path, sequence: int, out: str | Path, count: int = 8, scale: int = 1, columns: int = 4
) -> Path:
    """Write a PNG of ``count`` evenly spaced frames of sequence ``sequence`` (first and last included;
    every frame when the sequence is shorter), ``columns`` to a row, each as in :func:`sequence_video`.

    Raises:
        ValueError: one line naming the dataset (see :func:`read_sequence`), or on ``count < 1``.
    """
    if count < 1 or columns < 1:
        raise ValueError(f"count and columns must be positive, got {count}, {columns}")
    samples = read_sequence(dataset, sequence)
    picks = np.unique(np.round(np.linspace(0, len(samples) - 1, min(count, len(samples)))).astype(int))
    tiles = [_frame_image(samples[i], scale) for i in picks]
    cols = min(columns, len(tiles))
    rows = -(-len(tiles) // cols)
    tw, th = tiles[0].size
    doc = samples[0]["json"]
    kind = ((doc.get("camera") or {}).get("path") or {}).get("kind", "?")
    head = f"{Path(dataset).name}: sequence {sequence}, {doc['frames']} frames at {doc['fps']:g} fps"
    head += f", camera {kind}"
    sheet = Image.new("RGB", (cols * (tw + 4), 16 + rows * (th + 4)), (255, 255, 255))
    ImageDraw.Draw(sheet).text((3, 2), head, fill=(0, 0, 0))
    for i, tile in enumerate(tiles):
        sheet.paste(tile, ((i % cols) * (tw + 4), 16 + (i // cols) * (th + 4)))
    from blsm.io import atomic_write

    with atomic_write(out) as fh:
        sheet.save(fh, format="PNG")
    return Path(out)
