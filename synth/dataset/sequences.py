"""Clips of video sequences (``docs/video.md``) as a PyTorch dataset.

    ds = SequenceDataset("data/video", clip_len=16, stride=8, mode="person", crop=224, flip_prob=0.5)
    loader = DataLoader(ds, batch_size=8, num_workers=8, shuffle=True)

A clip is ``L = clip_len`` consecutive frames of one sequence; clips start every ``stride`` frames
and never cross a sequence (nor a gap, where a frame was skipped).

``mode="person"``: one clip per ``(sequence, track, start)``, kept when the person is ``in_view``
in at least ``min_in_view`` of its frames. Each frame is cropped as :class:`synth.dataset.images.SynthDataset`
crops (SPIN's square of side ``box_scale`` times the longer side of the person's visible ``box``,
``box_full`` when nothing is visible), with the crop's centre and side smoothed over the clip by a
centred moving average of ``smooth`` frames, so the crop follows the person without jitter.
``mode="frame"``: one clip per ``(sequence, start)``; each whole frame is fitted into the
``crop x crop`` square (the longer side fills it, the rest is zeros), with every person.

Items (float32 unless stated; ``L`` frames, ``K`` keypoints, ``S = crop``):

==========================  ================  =====================================================
``images``                  (L, 3, S, S)      in [0, 1]                                            
``keypoints_2d``            (L, K, 3)         crop pixels (centres at integer + 0.5) and visibility
                                              (visible in the image and inside the crop)
``keypoints_3d_cam``        (L, K, 3)         camera metres (of the camera below, not centred)
``keypoints_3d``            (L, K, 3)         world metres (Y up, ground ``y = 0``)
``velocity_3d``             (L, K, 3)         world m/s
``K``                       (L, 3, 3)         ``K_crop``: the intrinsics of the crop
``R``, ``t``                (L, 3, 3), (L, 3) world to camera, per frame
``transl``                  (L, 3)            BLSM ``transl``, world
``global_orient``           (L, 3)            BLSM ``global_orient``, world axis-angle
``pose``                    (L, 47)           BLSM unconstrained pose x
``bone``, ``shape``         (Kb,), (Ks,)      BLSM coefficients (one body per track)
``contact``                 (L, 9)            in :data:`CONTACT_REGIONS` order, 0 or 1
``contact_velocity``        (L, 9)            the velocity rule's contact, same order
``in_view``                 (L,) bool         at least one pixel of the person in the image
``time``                    (L,)              seconds from the sequence's start
``frame``                   (L,) int64        frame numbers in the sequence
``sequence``, ``track``     () int64          the sequence's id and the person's track
==========================  ================  =====================================================

In ``mode="frame"`` the person fields gain a people axis ``P`` after ``L`` (``keypoints_2d`` (L, P,
K, 3), ``transl`` (L, P, 3), ``in_view`` (L, P), ``bone`` (P, Kb), ...), padded with zeros to the
dataset's largest number of people so that clips batch; ``track`` is (P,) with -1 for padding and
``valid`` (P,) bool marks the real people.

Projection holds exactly (to float rounding): ``K_crop (R X + t) ~ keypoints_2d`` for the world
keypoints ``X``, and ``keypoints_3d_cam = R X + t``.

**Flip.** One draw per clip (probability ``flip_prob``, seeded like ``SynthDataset``) mirrors the
whole clip: every image left-right (``u -> W - u``), the keypoints swapped left/right by name
(:func:`synth.dataset.images.mirror_permutation`), the contact regions likewise, the pose by the model's
``dof_mirror``. The 3D labels stay a consistent, gravity-aligned world: the world is reflected by
``M = I - 2 n n^T`` with ``n`` the horizontal unit part of the first frame's camera x axis (world),
a reflection in a vertical plane, so Y stays up and the ground stays ``y = 0``, and each frame's
camera becomes ``R' = F R M``, ``t' = F t`` with ``F = diag(-1, 1, 1)`` (a proper rotation) and
the image's principal point ``cx' = W - cx``; so ``R' (M X) + t' = F (R X + t)``: the mirrored
world seen by the mirrored camera is the mirrored image. World keypoints and velocities become
``M X``, ``M v``; the body's orientation ``R_g' = M R_g B`` with ``B = diag(-1, 1, 1)`` the body's
own left-right mirror (the mirrored pose is the body mirrored in its own frame) and ``transl' =
M (transl + h) - h`` with ``h`` the model's root joint in the rest pose (the model rotates about
it), so that the model posed with the flipped labels gives the flipped keypoints (to the model's
1 mm left/right asymmetry of shape).

Raises:
    ValueError: one line naming the file, on a dataset that is not a sequence dataset or bad labels.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle

from blsm.skeleton import mirror_name
from synth.dataset import format as fmt
from synth.dataset.crops import crop_affine, warp_to_crop
from synth.dataset.format import CONTACT_REGIONS
from synth.dataset.images import SeededDataset, blsm_model, mirror_permutation, resolve_keypoints
from synth.dataset.index import DatasetIndex, check_png_crc
from synth.dataset.shards import MANIFEST

CONTACT_MIRROR = tuple(CONTACT_REGIONS.index(mirror_name(r)) for r in CONTACT_REGIONS)
"""``perm`` with ``CONTACT_REGIONS[perm[i]]`` the mirror of region ``i`` (left and right swapped)."""
MODES = ("person", "frame")
_READ = ("json", "rgb.png")
_FLIP = np.diag([-1.0, 1.0, 1.0])
_FLAGS = ("vis", "in_view", "frame")  # labels that are not real numbers
_PERSON = (
    "keypoints_2d", "keypoints_3d_cam", "keypoints_3d", "velocity_3d", "transl", "global_orient", "pose",
    "contact", "contact_velocity", "in_view",
)  # fmt: skip
"""The items with a people axis after the frames' in ``mode="frame"``."""


def world_mirror(R0: np.ndarray) -> np.ndarray:
    """``M = I - 2 n n^T`` (3, 3): the reflection in the vertical plane normal to ``n``, the
    horizontal unit part of the camera x axis of world-to-camera rotation ``R0`` (its row 0); the
    world x axis when that axis is vertical."""
    n = np.array([R0[0, 0], 0.0, R0[0, 2]], dtype=np.float64)
    norm = np.linalg.norm(n)
    n = n / norm if norm > 1e-9 else np.array([1.0, 0.0, 0.0])
    return np.eye(3) - 2.0 * np.outer(n, n)


def fill_missing_boxes(boxes: np.ndarray) -> np.ndarray:
    """Boxes (L, 4) with the rows of frames where the person has none (wholly behind the camera:
    ``box_full`` null) linearly interpolated from the frames that have one (the nearest at the ends)."""
    ok = np.isfinite(boxes).all(1)
    if ok.all() or not ok.any():
        return boxes
    idx = np.arange(len(boxes))
    return np.stack([np.interp(idx, idx[ok], boxes[ok, k]) for k in range(4)], 1)


def smooth_boxes(centres: np.ndarray, sides: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Centred moving average of (L, 2) crop centres and (L,) sides over ``window`` frames (the
    window shrinks at the clip's ends; ``window <= 1`` leaves them)."""
    if window <= 1:
        return centres, sides
    n, r = len(sides), window // 2
    lo, hi = np.maximum(np.arange(n) - r, 0), np.minimum(np.arange(n) + r + 1, n)
    csum = np.concatenate([np.zeros((1, 3)), np.cumsum(np.c_[centres, sides], axis=0)])
    mean = (csum[hi] - csum[lo]) / (hi - lo)[:, None]  # (L, 3)
    return mean[:, :2], mean[:, 2]


class SequenceDataset(SeededDataset):
    """Clips of ``clip_len`` frames of a sequence dataset (see the module docstring).

    Args:
        path: dataset folder of a sequence run (manifest with ``config.sequence.enabled``).
        clip_len: frames per clip, ``L``.
        stride: frames between the starts of consecutive clips of a sequence.
        mode: ``"person"`` (crops following one person) or ``"frame"`` (whole frames, all people).
        crop: output side in pixels.
        keypoints: ``"all"``, a model keypoint set (``"coco17"``, ...) or a list of names; closed
            under the left/right mirror.
        min_in_view: person mode: keep a clip when the person is in view in at least this fraction
            of its frames.
        box_scale: crop side over the box's longer side (1.2 as in SPIN).
        smooth: frames of the moving average of the crop's centre and side (person mode).
        flip_prob: probability of flipping a clip (one draw per clip).
        seed: None: fresh draws every call (torch's RNG, seeded per DataLoader worker); an int:
            clip ``i`` in epoch ``e`` (:meth:`set_epoch`) is a function of ``(seed, e, i)``.
        allow_incomplete: accept a manifest of an unfinished generation run.

    Raises:
        ValueError: one line naming the file, on a bad folder, manifest, shard or labels, or bad
            arguments.
    """

    def __init__(
        self,
        path: str | Path,
        clip_len: int = 16,
        stride: int = 8,
        mode: str = "person",
        crop: int = 224,
        keypoints: str | Sequence[str] = "all",
        *,
        min_in_view: float = 0.5,
        box_scale: float = 1.2,
        smooth: int = 5,
        flip_prob: float = 0.0,
        seed: int | None = None,
        allow_incomplete: bool = False,
    ) -> None:
        if mode not in MODES:
            raise ValueError(f"mode must be one of {list(MODES)}, got {mode!r}")
        if clip_len < 1 or stride < 1 or crop < 1 or box_scale <= 0:
            raise ValueError(
                "clip_len, stride, crop and box_scale must be positive, "
                f"got {clip_len}, {stride}, {crop}, {box_scale}"
            )
        if not (0 <= min_in_view <= 1 and 0 <= flip_prob <= 1):
            raise ValueError(f"min_in_view and flip_prob must be in [0, 1], got {min_in_view}, {flip_prob}")
        self.clip_len, self.stride, self.mode, self.crop = int(clip_len), int(stride), mode, int(crop)
        self.box_scale, self.smooth, self.flip_prob = float(box_scale), int(smooth), float(flip_prob)
        self.seed, self.epoch = seed, 0
        self.index = DatasetIndex(path, allow_incomplete, required=_READ)
        frames = self._frames_per_sequence()
        by_seq: dict[int, dict[int, int]] = {}
        for i, (_, key, _) in enumerate(self.index.samples):
            s, f = divmod(int(key), frames)
            by_seq.setdefault(s, {})[f] = i
        if not by_seq:
            raise ValueError(f"{self.index.root}: the dataset holds no samples")
        names: list[str] | None = None
        self.items: list[tuple[int, tuple[int, ...], int]] = []  # (sequence, sample indices, track or -1)
        self.max_people = 0
        for s in sorted(by_seq):
            samples = by_seq[s]
            # person mode needs every frame's in_view; frame mode only the first frame's people
            looked = sorted(samples) if mode == "person" else [min(samples)]
            in_view = []
            for f in looked:
                meta = self.index.json(samples[f])
                try:
                    if names is None:
                        names = list(meta["keypoint_names"])
                        sel = resolve_keypoints(names, keypoints)
                    elif meta["keypoint_names"] != names:
                        raise ValueError("keypoint_names differ from the first sample's")
                    if meta["sequence"] != s or meta["frame"] != f:
                        raise ValueError(
                            f"sequence/frame {meta['sequence']}/{meta['frame']}, key says {s}/{f}"
                        )
                    in_view.append([bool(q["in_view"]) for q in meta["people"]])
                except (KeyError, IndexError, TypeError, ValueError) as exc:
                    raise ValueError(f"{self.index.where(samples[f])}.json: bad labels ({exc})") from None
                if len(in_view[-1]) != len(in_view[0]):
                    raise ValueError(
                        f"{self.index.where(samples[f])}.json: {len(in_view[-1])} people, frame "
                        f"{looked[0]} of the sequence has {len(in_view[0])} (every frame lists everyone)"
                    )
            people = len(in_view[0])
            self.max_people = max(self.max_people, people)
            view = dict(zip(looked, np.asarray(in_view, bool).reshape(len(looked), people), strict=True))
            for start in self._starts(sorted(samples)):
                clip = tuple(samples[f] for f in range(start, start + self.clip_len))
                if mode == "frame":
                    self.items.append((s, clip, -1))
                    continue
                seen = np.stack([view[f] for f in range(start, start + self.clip_len)])  # (L, P)
                self.items.extend((s, clip, p) for p in range(people) if seen[:, p].mean() >= min_in_view)
        assert names is not None
        self.keypoint_names = [names[k] for k in sel]
        self._sel = np.asarray(sel)
        self._kp_perm = np.asarray(mirror_permutation(self.keypoint_names))
        model = blsm_model()
        perm, sign = model.dof_mirror
        self._dof_perm, self._dof_sign = perm.numpy().copy(), sign.numpy().astype(np.float64)
        self._root = model.heads[0].double().numpy()  # the joint global_orient turns about (rest pose)
        self.index.close()

    def _frames_per_sequence(self) -> int:
        man_path = self.index.root / MANIFEST
        try:
            seq = json.loads(man_path.read_text())["config"]["sequence"]
            enabled, frames = seq["enabled"], int(seq["frames"])
        except (KeyError, TypeError, ValueError):
            raise ValueError(
                f"{man_path}: no config.sequence (enabled, frames): not a sequence dataset"
            ) from None
        if not enabled or frames < 1:
            raise ValueError(f"{man_path}: config.sequence is not enabled: not a sequence dataset")
        return frames

    def _starts(self, frames: list[int]) -> list[int]:
        """Clip starts over the runs of consecutive frame numbers of a sequence."""
        out, run = [], [frames[0]]
        for f in [*frames[1:], None]:
            if f is not None and f == run[-1] + 1:
                run.append(f)
                continue
            out += list(range(run[0], run[-1] - self.clip_len + 2, self.stride))
            if f is not None:
                run = [f]
        return out

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return self.get(i, flip=bool(self.item_rng(i).uniform() < self.flip_prob))

    def get(self, i: int, flip: bool = False) -> dict[str, torch.Tensor]:
        """Clip ``i``, flipped or not (``__getitem__`` draws ``flip``)."""
        s, samples, track = self.items[i]
        rgbs, metas = zip(*(self._read(j) for j in samples), strict=True)
        lab = self._labels(samples, metas, [track] if track >= 0 else None)
        h, w = rgbs[0].shape[:2]
        n = len(samples)
        if track >= 0:
            boxes = fill_missing_boxes(np.asarray(lab["box"][:, 0], np.float64))  # (L, 4)
            centres = (boxes[:, :2] + boxes[:, 2:]) / 2
            sides = np.maximum((boxes[:, 2:] - boxes[:, :2]).max(1), 1.0) * self.box_scale
            centres, sides = smooth_boxes(centres, sides, self.smooth)
        else:
            centres, sides = np.tile([w / 2, h / 2], (n, 1)), np.full(n, float(max(w, h)))
        amat = np.stack(
            [crop_affine(c, z, self.crop, 0.0, flip) for c, z in zip(centres, sides, strict=True)]
        )
        images = torch.stack(
            [
                warp_to_crop(torch.tensor(x).permute(2, 0, 1).float() / 255.0, a, self.crop)
                for x, a in zip(rgbs, amat, strict=True)
            ]
        )

        uv = np.einsum("lij,lpkj->lpki", amat[:, :2, :2], lab["kp2"]) + amat[:, None, None, :2, 2]
        vis = lab["vis"] & (uv >= 0).all(-1) & (uv < self.crop).all(-1)
        flip_cam = _FLIP if flip else np.eye(3)
        mirror = world_mirror(lab["R"][0]) if flip else np.eye(3)
        body = _FLIP if flip else np.eye(3)
        kp3 = lab["kp3"] @ mirror.T
        vel = lab["vel"] @ mirror.T
        kpc = lab["kpc"] @ flip_cam.T
        rot = flip_cam @ lab["R"] @ mirror
        tvec = lab["t"] @ flip_cam.T
        kcrop = amat @ lab["K"] @ flip_cam
        transl = (lab["transl"] + self._root) @ mirror.T - self._root
        orient = mirror @ lab["orient"] @ body  # (L, P, 3, 3)
        pose, contact, contact_v = lab["pose"], lab["contact"], lab["contact_velocity"]
        if flip:
            kp = self._kp_perm
            uv, kp3, vel, kpc = (x[..., kp, :] for x in (uv, kp3, vel, kpc))
            vis = vis[..., kp]
            pose = pose[..., self._dof_perm] * self._dof_sign
            contact, contact_v = contact[..., CONTACT_MIRROR], contact_v[..., CONTACT_MIRROR]
        aa = rotation_matrix_to_axis_angle(torch.from_numpy(orient.reshape(-1, 3, 3))).reshape(transl.shape)

        def f32(x: Any) -> torch.Tensor:
            return torch.as_tensor(np.asarray(x, np.float64), dtype=torch.float32)

        out = {
            "images": images,
            "keypoints_2d": torch.cat([f32(uv), f32(vis)[..., None]], -1),
            "keypoints_3d_cam": f32(kpc),
            "keypoints_3d": f32(kp3),
            "velocity_3d": f32(vel),
            "K": f32(kcrop),
            "R": f32(rot),
            "t": f32(tvec),
            "transl": f32(transl),
            "global_orient": aa.float(),
            "pose": f32(pose),
            "bone": f32(lab["bone"]),
            "shape": f32(lab["shape"]),
            "contact": f32(contact),
            "contact_velocity": f32(contact_v),
            "in_view": torch.from_numpy(lab["in_view"]),
            "time": f32(lab["time"]),
            "frame": torch.from_numpy(lab["frame"]),
            "sequence": torch.tensor(s),
        }
        if track >= 0:
            for k in _PERSON:
                out[k] = out[k][:, 0]
            out["bone"], out["shape"], out["track"] = out["bone"][0], out["shape"][0], torch.tensor(track)
            return out
        people = out["in_view"].shape[1]
        pad = self.max_people - people
        for k in _PERSON:
            out[k] = torch.cat([out[k], out[k].new_zeros((n, pad, *out[k].shape[2:]))], 1)
        for k in ("bone", "shape"):
            out[k] = torch.cat([out[k], out[k].new_zeros((pad, *out[k].shape[1:]))], 0)
        out["track"] = torch.cat([torch.arange(people), torch.full((pad,), -1)])
        out["valid"] = out["track"] >= 0
        return out

    def _read(self, j: int) -> tuple[np.ndarray, dict[str, Any]]:
        where = self.index.where(j)
        raw = self.index.read(j, _READ)
        check_png_crc(raw["rgb.png"], f"{where}.rgb.png")
        rgb = fmt.decode_png(raw["rgb.png"], f"{where}.rgb.png")
        if rgb.ndim != 3:
            raise ValueError(f"{where}.rgb.png: not an RGB image ({rgb.shape})")
        return rgb, fmt.decode_json(raw["json"], f"{where}.json")

    def _labels(
        self, samples: Sequence[int], metas: Sequence[dict[str, Any]], tracks: list[int] | None
    ) -> dict[str, np.ndarray]:
        """The labels of the clip's frames as arrays (L, P, ...) of the ``tracks`` (None: everyone)."""
        rows: dict[str, list[Any]] = {}
        for j, meta in zip(samples, metas, strict=True):
            try:
                people = meta["people"]
                chosen = [people[p] for p in (range(len(people)) if tracks is None else tracks)]
                if tracks is None and rows.get("frame") and len(chosen) != len(rows["in_view"][0]):
                    raise ValueError("the number of people differs from the clip's first frame")
                cam = meta["camera"]
                per = {
                    "box": [fmt.person_box(q) if q.get("box") or q.get("box_full") else (np.nan,) * 4 for q in chosen],
                    "kp2": [np.asarray(q["keypoints_2d"], np.float64)[self._sel] for q in chosen],
                    "vis": [fmt.seen_keypoints(q)[self._sel] for q in chosen],
                    "kp3": [np.asarray(q["keypoints_3d"], np.float64)[self._sel] for q in chosen],
                    "kpc": [np.asarray(q["keypoints_3d_cam"], np.float64)[self._sel] for q in chosen],
                    "vel": [np.asarray(q["velocity_3d"], np.float64)[self._sel] for q in chosen],
                    "transl": [q["blsm"]["transl"] for q in chosen],
                    "orient": [q["blsm"]["global_orient"] for q in chosen],
                    "pose": [q["blsm"]["pose"] for q in chosen],
                    "bone": [q["blsm"]["bone"] for q in chosen],
                    "shape": [q["blsm"]["shape"] for q in chosen],
                    "contact": [[q["contact"][r] for r in CONTACT_REGIONS] for q in chosen],
                    "contact_velocity": [[q["contact_velocity"][r] for r in CONTACT_REGIONS] for q in chosen],
                    "in_view": [q["in_view"] for q in chosen],
                    "K": cam["K"],
                    "R": cam["R"],
                    "t": cam["t"],
                    "time": meta["time"],
                    "frame": meta["frame"],
                }
                for k, v in per.items():
                    rows.setdefault(k, []).append(v)
            except (KeyError, IndexError, TypeError, ValueError) as exc:
                raise ValueError(f"{self.index.where(j)}.json: bad labels ({exc})") from None
        try:
            out = {k: np.asarray(v, np.float64) for k, v in rows.items() if k not in _FLAGS}
            out.update(vis=np.asarray(rows["vis"], bool), in_view=np.asarray(rows["in_view"], bool))
            out["frame"] = np.asarray(rows["frame"], np.int64)
            out["bone"], out["shape"] = out["bone"][0], out["shape"][0]  # one body per track: (P, Kb)
            shapes = {"K": (3, 3), "R": (3, 3), "t": (3,), "pose": (len(self._dof_perm),), "transl": (3,)}
            for k, want in shapes.items():
                if out[k].shape[-len(want) :] != want:
                    raise ValueError(f"{k} must be {want} per frame, got {out[k].shape[1:]}")
            rot = axis_angle_to_rotation_matrix(torch.from_numpy(out["orient"].reshape(-1, 3))).numpy()
            out["orient"] = rot.reshape(*out["transl"].shape, 3)  # (L, P, 3, 3)
        except ValueError as exc:
            raise ValueError(f"{self.index.where(samples[0])}.json: bad labels in the clip ({exc})") from None
        return out
