"""A PyTorch dataset of person crops from a generated dataset folder, HMR/SPIN style.

    ds = SynthDataset("data/train", crop=224)
    loader = DataLoader(ds, batch_size=64, num_workers=8, shuffle=True)

SPIN-style random crops (scale, rotation, flip, shift, colour) of the same items:
``recovery.datasets.augment.AugmentedDataset(ds, AugmentConfig())``; it calls :meth:`SynthDataset.get`
with each item's crop geometry, which this module keeps exact.

One item is one person instance of one image (``person="all"``, the default, as HMR and SPIN do);
persons with fewer than ``min_pixels`` visible mask pixels or fewer than ``min_visible`` visible
keypoints are skipped. ``person="largest"`` gives one item per image instead: its person with the
most visible pixels among those that pass the same filters.

The crop is a square around the centre of the person's visible ``box`` (``box_full`` when nothing
is visible) of side ``max(w, h) * box_scale * scale``, resized to ``crop x crop``. One affine map
``A`` (3, 3) from original to crop pixel coordinates, pixel centres at integer + 0.5 in both, moves
the image (bilinear), the person's mask and parts (nearest) and the keypoints; the in-plane rotation
is the camera's rotation ``Rz`` about its z axis and the flip the mirror ``M = diag(-1, 1, 1)``, so
with ``L = M Rz`` (``M = I`` without flip): ``keypoints_3d = L (X - X_pelvis)``, ``transl_cam = L
X_pelvis``, ``global_orient = L R R_global M`` and ``K_crop = A K L^T``, so that ``K_crop
(keypoints_3d + transl_cam)`` projects onto ``keypoints_2d`` exactly. A flip also swaps left and
right keypoints (by name, :func:`blsm.skeleton.mirror_name`) and part labels, and mirrors the pose
with the model's ``dof_mirror``. Because the DoF table makes every atom's mirrored range the signed
image of its own (checked when the table is read), Eq. 6 commutes with the mirror and the
unconstrained ``pose`` mirrors by the same permutation and signs as ``angles``, exactly; ``bone``
and ``shape`` are kept (the model's shape spaces are left/right symmetric to 1 mm).

Items (float32 unless stated): ``image`` (3, crop, crop) in [0, 1] (a backbone normalises its own
input), ``keypoints_2d`` (K, 3) crop pixels and visibility (visible in the image and
inside the crop), ``keypoints_3d`` (K, 3) camera metres relative to the pelvis, ``pose`` (47,),
``angles`` (47,) radians, ``bone`` (Kb,), ``shape`` (Ks,), ``global_orient`` (3,) camera-frame
axis-angle, ``transl_cam`` (3,) metres, ``K_crop`` (3, 3), ``affine`` (3, 3) the map ``A``,
``mask`` (crop, crop) bool, ``parts`` (crop, crop) int64 (0 background, 1 + ``PART_NAMES`` index),
``index`` (sample index) and ``person`` (int64).

Datasets made with the optional body labels (:mod:`synth.contacts`) add, for every item:
``contact_parts`` (6,) 1 where that part (``PART_NAMES`` order, swapped with a flip) of the person
is within the contact distance of another person's body (``labels.contact_distance``;
:meth:`SynthDataset.contacts` gives the vertex lists), and ``occupancy`` (N, 4): the person's
occupancy points in the crop's camera frame (``L x``, the frame of ``transl_cam``) and their
inside flag (``labels.occupancy``).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle

from blsm.skeleton import mirror_name
from synth.dataset import format as fmt
from synth.dataset.crops import camera_rotation, crop_affine, map_points, warp_to_crop
from synth.dataset.index import IMAGE_FIELDS, DatasetIndex, check_png_crc

__all__ = ["SeededDataset", "SynthDataset", "blsm_model", "mirror_permutation", "resolve_keypoints"]

_PART_SWAP = torch.tensor([0] + [1 + fmt.PART_NAMES.index(mirror_name(n)) for n in fmt.PART_NAMES])



@functools.cache
def blsm_model() -> Any:
    import blsm

    return blsm.load()


def resolve_keypoints(names: Sequence[str], keypoints: str | Sequence[str]) -> list[int]:
    """Indices into ``names`` of ``"all"``, a model keypoint set (``"coco17"``, ...) or a name list."""
    if isinstance(keypoints, str) and keypoints == "all":
        return list(range(len(names)))
    if isinstance(keypoints, str):
        sets = blsm_model().keypoint_sets
        if keypoints not in sets:
            raise ValueError(f"unknown keypoint set {keypoints!r}; known: 'all', {sorted(sets)}")
        keypoints = [blsm_model().keypoint_names[k] for k in sets[keypoints]]
    missing = [n for n in keypoints if n not in names]
    if missing:
        raise ValueError(f"keypoints {missing} are not in the dataset's keypoint_names")
    return [list(names).index(n) for n in keypoints]


def mirror_permutation(names: Sequence[str]) -> list[int]:
    """``perm`` with ``names[perm[k]] == mirror_name(names[k])``; a missing partner is a ValueError."""
    perm = []
    for n in names:
        partner = mirror_name(n)
        if partner not in names:
            raise ValueError(f"keypoint {n!r} has no mirror partner {partner!r} in the selection")
        perm.append(list(names).index(partner))
    return perm


class SeededDataset(torch.utils.data.Dataset):
    """A dataset of ``items`` whose random draws (augmentation, flips) are a function of ``(seed,
    epoch, index)`` when ``seed`` is set, and fresh otherwise."""

    items: list[Any]
    seed: int | None = None
    epoch: int = 0

    def __len__(self) -> int:
        return len(self.items)

    def set_epoch(self, epoch: int) -> None:
        """Select the epoch of seeded draws (takes effect in workers started afterwards)."""
        self.epoch = int(epoch)

    def item_rng(self, i: int) -> np.random.Generator:
        """The random generator of item ``i`` in this epoch."""
        seed = [self.seed, self.epoch, i] if self.seed is not None else int(torch.randint(0, 2**62, ()))
        return np.random.default_rng(seed)


class SynthDataset(torch.utils.data.Dataset):
    """Person crops with 2D/3D keypoints, BLSM parameters and masks (see the module docstring).

    Args:
        path: dataset folder (``manifest.json`` and ``shard-*.tar``).
        crop: output side in pixels.
        person: ``"all"`` (one item per person instance) or ``"largest"`` (one item per image).
        keypoints: ``"all"`` (every keypoint of the samples' ``keypoint_names``), a model keypoint
            set (``"coco17"``, ``"blsm_joints"``) or a list of names; it must be closed under the
            left/right mirror.
        box_scale: crop side over the box's longer side before augmentation (1.2 as in SPIN).
        min_pixels: skip persons with fewer visible mask pixels.
        min_visible: skip persons with fewer visible selected keypoints.
        allow_incomplete: accept a manifest of an unfinished generation run.
        antialias: prefilter a crop that shrinks its image (:func:`warp_to_crop`; off: bilinear
            sampling alone, as before 2026-12-02).

    Raises:
        ValueError: one line naming the file, on a bad folder, manifest, shard or sample.
    """

    def __init__(
        self,
        path: str | Path,
        crop: int = 224,
        person: str = "all",
        keypoints: str | Sequence[str] = "all",
        *,
        box_scale: float = 1.2,
        min_pixels: int = 1,
        min_visible: int = 0,
        allow_incomplete: bool = False,
        antialias: bool = True,
    ) -> None:
        if person not in ("all", "largest"):
            raise ValueError(f"person must be 'all' or 'largest', got {person!r}")
        if crop < 1 or box_scale <= 0:
            raise ValueError(f"crop and box_scale must be positive, got {crop}, {box_scale}")
        self.crop, self.box_scale, self.antialias = int(crop), float(box_scale), bool(antialias)
        self.index = DatasetIndex(path, allow_incomplete)
        extra = self.index.config.get("labels") or {}
        self.has_contacts, self.has_occupancy = bool(extra.get("contact_distance")), bool(extra.get("occupancy"))
        self.items: list[tuple[int, int]] = []
        names: list[str] | None = None
        for i in range(len(self.index)):
            meta = self.index.json(i)
            try:
                if names is None:
                    names = list(meta["keypoint_names"])
                    sel = resolve_keypoints(names, keypoints)
                elif meta["keypoint_names"] != names:
                    raise ValueError("keypoint_names differ from the first sample's")
                people = meta["people"]
                ok = [p for p, q in enumerate(people) if q["pixels"] >= min_pixels]
                ok = [p for p in ok if fmt.seen_keypoints(people[p])[sel].sum() >= min_visible]
            except (KeyError, IndexError, TypeError, ValueError) as exc:
                raise ValueError(f"{self.index.where(i)}.json: bad labels ({exc})") from None
            if person == "largest" and ok:
                ok = [max(ok, key=lambda p: people[p]["pixels"])]
            self.items.extend((i, p) for p in ok)
        if names is None:
            raise ValueError(f"{self.index.root}: the dataset holds no samples")
        if "pelvis" not in names:
            raise ValueError(f"{self.index.root}: keypoint_names has no 'pelvis'")
        self.keypoint_names = [names[k] for k in sel]
        self._sel, self._pelvis = np.asarray(sel), names.index("pelvis")
        self._kp_perm = np.asarray(mirror_permutation(self.keypoint_names))
        perm, sign = blsm_model().dof_mirror
        self._dof_perm, self._dof_sign = perm.numpy().copy(), sign.numpy().astype(np.float64)
        self.index.close()

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return self.get(i)

    def get(self, i: int, scale: float = 1.0, rotation_deg: float = 0.0, flip: bool = False,
            shift: tuple[float, float] = (0.0, 0.0)) -> dict[str, torch.Tensor]:
        """Item ``i`` cropped with the side times ``scale``, the content turned by ``rotation_deg``
        (counter-clockwise on screen), mirrored with ``flip`` and the centre moved by ``shift`` times
        the side; the defaults give the plain centred crop (``__getitem__``)."""
        s, p = self.items[i]
        rgb, own, parts, lab = self._read(s, p)
        x0, y0, x1, y1 = lab["box"]
        side = max(x1 - x0, y1 - y0, 1.0) * self.box_scale * scale
        center = ((x0 + x1) / 2 + shift[0] * side, (y0 + y1) / 2 + shift[1] * side)
        amat = crop_affine(center, side, self.crop, rotation_deg, flip)
        lmat = camera_rotation(rotation_deg, flip)
        mirror = np.diag([-1.0 if flip else 1.0, 1.0, 1.0])

        image = warp_to_crop(torch.tensor(rgb).permute(2, 0, 1).float() / 255.0, amat, self.crop,
                             antialias=self.antialias)
        labels = torch.from_numpy(np.stack([own, np.where(own, parts, 0)]).astype(np.float32))
        labels = warp_to_crop(labels, amat, self.crop, mode="nearest")
        part_map = labels[1].round().long()

        uv = map_points(lab["kp2"], amat)  # (K, 2)
        vis = lab["vis"] & (uv >= 0).all(1) & (uv < self.crop).all(1)
        pelvis = lab["kp3"][self._pelvis]
        rel = (lab["kp3"][self._sel] - pelvis) @ lmat.T  # (K, 3)
        orient = lmat @ lab["R"] @ lab["orient"] @ mirror
        pose, angles = lab["pose"], lab["angles"]
        if flip:
            uv, vis, rel = uv[self._kp_perm], vis[self._kp_perm], rel[self._kp_perm]
            part_map = _PART_SWAP[part_map]
            pose, angles = pose[self._dof_perm] * self._dof_sign, angles[self._dof_perm] * self._dof_sign

        def f32(x: Any) -> torch.Tensor:
            return torch.as_tensor(np.asarray(x, np.float64), dtype=torch.float32)

        out = {} if not (self.has_contacts or self.has_occupancy) else self._body_labels(s, p, lmat, flip)
        return out | {
            "image": image,
            "keypoints_2d": torch.cat([f32(uv), f32(vis)[:, None]], 1),
            "keypoints_3d": f32(rel),
            "pose": f32(pose),
            "angles": f32(angles),
            "bone": f32(lab["bone"]),
            "shape": f32(lab["shape"]),
            "global_orient": f32(rotation_matrix_to_axis_angle(torch.from_numpy(orient)[None])[0]),
            "transl_cam": f32(lmat @ pelvis),
            "K_crop": f32(amat @ lab["K"] @ lmat.T),
            "affine": f32(amat),
            "mask": labels[0] > 0.5,
            "parts": part_map,
            "index": torch.tensor(lab["index"]),
            "person": torch.tensor(p),
        }

    def contacts(self, i: int) -> list[dict[str, Any]]:
        """Item ``i``'s person's contacts (:mod:`synth.contacts`): per other person ``with``, its
        own ``vertices`` and ``parts`` within the contact distance, the ``distance`` and ``closest_mm``."""
        s, p = self.items[i]
        out = []
        for e in self.index.json(s).get("contacts") or []:
            if p in e["people"]:
                k = e["people"].index(p)
                out.append({"with": e["people"][1 - k], "vertices": e["vertices"][k], "parts": e["parts"][k],
                            "distance": e["distance"], "closest_mm": e["closest_mm"]})
        return out

    def _body_labels(self, s: int, p: int, lmat: np.ndarray, flip: bool) -> dict[str, torch.Tensor]:
        """``contact_parts`` and ``occupancy`` of person ``p`` of sample ``s`` (module docstring)."""
        out = {}
        where = self.index.where(s)
        if self.has_contacts:
            touched = np.zeros(len(fmt.PART_NAMES), np.float32)
            for e in self.index.json(s).get("contacts") or []:
                if p in e["people"]:
                    for name in e["parts"][e["people"].index(p)]:
                        touched[fmt.PART_NAMES.index(name)] = 1.0
            if flip:
                touched = touched[_PART_SWAP[1:].numpy() - 1]
            out["contact_parts"] = torch.from_numpy(touched)
        if self.has_occupancy:
            occ = fmt.decode_npy_gz(self.index.read(s, ("occupancy.npy.gz",))["occupancy.npy.gz"], f"{where}.occupancy.npy.gz")
            if occ.ndim != 3 or p >= len(occ) or occ.shape[2] != 4:
                raise ValueError(f"{where}.occupancy.npy.gz: not (P, N, 4) for person {p}")
            q = occ[p].astype(np.float64)
            out["occupancy"] = torch.from_numpy(np.concatenate([q[:, :3] @ lmat.T, q[:, 3:]], 1).astype(np.float32))
        return out

    def _read(self, s: int, p: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Sample ``s``'s image (H, W, 3), person ``p``'s mask (H, W) bool, the parts (H, W) and labels."""
        where = self.index.where(s)
        raw = self.index.read(s, IMAGE_FIELDS)
        meta = fmt.decode_json(raw["json"], f"{where}.json")
        for name in ("rgb.png", "mask.png", "parts.png"):
            check_png_crc(raw[name], f"{where}.{name}")
        rgb = fmt.decode_png(raw["rgb.png"], f"{where}.rgb.png")
        mask = fmt.decode_png(raw["mask.png"], f"{where}.mask.png")
        parts = fmt.decode_png(raw["parts.png"], f"{where}.parts.png")
        if rgb.ndim != 3 or mask.shape != rgb.shape[:2] or parts.shape != rgb.shape[:2]:
            raise ValueError(f"{where}: image sizes differ: {rgb.shape}, {mask.shape}, {parts.shape}")
        try:
            q, cam, b = meta["people"][p], meta["camera"], meta["people"][p]["blsm"]
            orient = torch.tensor([b["global_orient"]], dtype=torch.float64)
            lab = {
                "box": fmt.person_box(q),
                "kp2": np.asarray(q["keypoints_2d"], np.float64)[self._sel],
                "vis": fmt.seen_keypoints(q)[self._sel],
                "kp3": np.asarray(q["keypoints_3d_cam"], np.float64),
                "K": np.asarray(cam["K"], np.float64),
                "R": np.asarray(cam["R"], np.float64),
                "orient": axis_angle_to_rotation_matrix(orient)[0].numpy(),
                "pose": np.asarray(b["pose"], np.float64),
                "angles": np.asarray(b["angles"], np.float64),
                "bone": b["bone"],
                "shape": b["shape"],
                "index": int(meta["index"]),
            }
            if lab["pose"].shape != self._dof_perm.shape or lab["angles"].shape != self._dof_perm.shape:
                raise ValueError(f"pose and angles must be {self._dof_perm.shape}")
            if lab["K"].shape != (3, 3) or lab["R"].shape != (3, 3):
                raise ValueError("camera K and R must be 3x3")
        except (KeyError, IndexError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}.json: bad labels of person {p} ({exc})") from None
        return rgb, mask == p + 1, parts, lab