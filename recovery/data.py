"""Training data: pre-cropped caches of ``synth`` datasets, per-batch augmentation, resumable order.

Decoding a PNG and warping it per item costs more CPU than a small network's step on two cores, so
training reads a **cache**: every person of a dataset cropped once by :class:`synth.data.SynthDataset`
(no augmentation) at ``context`` times the training crop's field of view, stored as uint8 arrays
(``images.npy`` (N, S, S, 3), ``masks.npy`` and ``parts.npy`` (N, S, S)) and the labels
(``labels.npz``), with ``meta.json`` written last. A cache is rebuilt when its dataset's manifest or
the crop settings change, and is written into a temporary folder renamed when complete.

Augmentation happens per batch (in the loader worker) with the geometry of
:meth:`synth.data.SynthDataset.get`: a second affine map ``A2`` from cache to crop pixels
(scale, in-plane rotation, flip, translation; pixel centres at integer + 0.5), the camera-frame map
``L = M Rz``, so ``keypoints_3d <- L keypoints_3d``, ``transl <- L transl``, ``R_global <- L R_global M``
and ``K <- A2 K L^T``; a flip swaps left and right keypoints and parts and mirrors the 47 atoms with
the model's ``dof_mirror``. So ``K (keypoints_3d + transl)`` projects onto ``keypoints_2d`` exactly
after augmentation too. Each item's augmentation is a function of ``(seed, epoch, item)`` only, and
:class:`ResumableSampler` gives the order of ``(seed, epoch)`` from any position: a resumed run sees
the same batches as an uninterrupted one; :class:`ShardedBatches` splits each batch of that order
over the processes of a ``torchrun`` run (so the split changes neither the batches nor, the
augmentation being per item, the crops).
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math
import shutil
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from kornia.geometry.transform import warp_affine

from blsm.io import sha256_file
from blsm.skeleton import mirror_name
from synth import format as fmt
from synth.data import AugmentConfig, CropParams, SynthDataset, camera_rotation, crop_affine, draw_params
from synth.shards import MANIFEST

CACHE_FORMAT = "recovery-crop-cache"
CACHE_VERSION = 1
VIEWS = ("normal", "rare")


def _cache_key(dataset: Path, side: int, box_scale: float) -> dict[str, Any]:
    return {"format": CACHE_FORMAT, "version": CACHE_VERSION, "manifest_sha256": sha256_file(dataset / MANIFEST),
            "side": side, "box_scale": box_scale}


def cache_folder(dataset: str | Path, cache_root: str | Path, crop: int, context: float) -> Path:
    """Where the cache of ``dataset`` for this crop lives: ``cache_root/<name>-<hash>``."""
    dataset = Path(dataset)
    h = hashlib.sha256(f"{dataset.resolve()}|{crop}|{context}".encode()).hexdigest()[:10]
    return Path(cache_root) / f"{dataset.name}-{h}"


def build_cache(dataset: str | Path, out: str | Path, crop: int, context: float, workers: int = 2,
                log: Any = print) -> Path:
    """Crop every person of ``dataset`` once into ``out`` (module docstring); reuse a valid cache.

    The cache crop has side ``S = round(crop * context)`` pixels and covers ``1.2 * context`` times
    the person's box (SPIN's 1.2 for the training crop), so the un-augmented training crop is its
    centre ``S / context`` pixels.

    Raises:
        ValueError: one line naming the file, on a missing, empty or malformed dataset.
    """
    dataset, out = Path(dataset), Path(out)
    side = int(round(crop * context))
    box_scale = 1.2 * context
    if not (dataset / MANIFEST).is_file():
        raise ValueError(f"{dataset / MANIFEST}: no dataset manifest here")
    key = _cache_key(dataset, side, box_scale)
    meta_path = out / "meta.json"
    if meta_path.is_file():
        meta = json.loads(meta_path.read_text())
        if all(meta.get(k) == v for k, v in key.items()):
            return out
        log(f"[recovery] {out}: cache is stale (dataset or crop changed); rebuilding")
    ds = SynthDataset(dataset, crop=side, augment=None, box_scale=box_scale)
    n = len(ds)
    if n == 0:
        raise ValueError(f"{dataset}: the dataset holds no usable person")
    tmp = out.with_name(f".{out.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        _write_cache(ds, tmp, key, dataset, crop, context, side, workers, log)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)  # a bad sample found while cropping leaves nothing
        raise
    shutil.rmtree(out, ignore_errors=True)
    tmp.rename(out)
    log(f"[recovery] cache {out}: {n} people, {side} px")
    return out


def _write_cache(ds: SynthDataset, tmp: Path, key: dict[str, Any], dataset: Path, crop: int, context: float,
                 side: int, workers: int, log: Any) -> None:
    n = len(ds)
    images = np.lib.format.open_memmap(tmp / "images.npy", "w+", np.uint8, (n, side, side, 3))
    masks = np.lib.format.open_memmap(tmp / "masks.npy", "w+", np.uint8, (n, side, side))
    parts = np.lib.format.open_memmap(tmp / "parts.npy", "w+", np.uint8, (n, side, side))
    lab: dict[str, np.ndarray] = {}
    info = person_info(ds)
    loader = torch.utils.data.DataLoader(ds, batch_size=64, num_workers=workers, collate_fn=_stack)
    done = 0
    for batch in loader:
        b = batch["image"].shape[0]
        images[done : done + b] = (batch["image"].permute(0, 2, 3, 1) * 255.0 + 0.5).clamp(0, 255).byte().numpy()
        masks[done : done + b] = batch["mask"].numpy()
        parts[done : done + b] = batch["parts"].numpy()
        for name in ("keypoints_2d", "keypoints_3d", "pose", "angles", "bone", "shape", "global_orient",
                     "transl_cam", "K_crop", "index", "person"):
            arr = batch[name].numpy()
            if name not in lab:
                lab[name] = np.zeros((n, *arr.shape[1:]), arr.dtype)
            lab[name][done : done + b] = arr
        done += b
        if done % 2048 < b:
            log(f"[recovery] cache {dataset.name}: {done}/{n} people")
    images.flush(), masks.flush(), parts.flush()
    del images, masks, parts
    np.savez(tmp / "labels.npz", **lab, **info)
    meta = {**key, "dataset": str(dataset), "count": n, "crop": crop, "context": context,
            "keypoint_names": ds.keypoint_names}
    (tmp / "meta.json").write_text(json.dumps(meta, indent=1))


def _stack(items: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    return {k: torch.stack([it[k] for it in items]) for k in items[0]}


def person_info(ds: SynthDataset) -> dict[str, np.ndarray]:
    """Per item: view (0 normal, 1 rare), truncated, people in the image, subject id."""
    view, trunc, people, subject = [], [], [], []
    last, meta = -1, {}
    for s, p in ds.items:  # the people of one image are consecutive: read its labels once
        if s != last:
            last, meta = s, ds.index.json(s)
        cam = meta["camera"].get("info", {})
        view.append(VIEWS.index(cam.get("view", "normal")) if cam.get("view", "normal") in VIEWS else 1)
        trunc.append(bool(cam.get("truncated", False)))
        people.append(len(meta["people"]))
        subject.append(str(meta["people"][p]["subject"]))
    ds.index.close()
    return {"view": np.asarray(view, np.int64), "truncated": np.asarray(trunc), "people": np.asarray(people, np.int64),
            "subject": np.asarray(subject)}


class CropCache(torch.utils.data.Dataset):
    """One or more caches as one dataset of un-augmented items (uint8 images).

    Items are keyed by ``(epoch, i)`` (from :class:`ResumableSampler`) or by ``i``; each carries the
    key so that :class:`BatchAugment` can seed its augmentation.
    """

    def __init__(self, folders: Sequence[str | Path]) -> None:
        self.folders = [Path(f) for f in folders]
        self.parts: list[dict[str, Any]] = []
        names = None
        for f in self.folders:
            meta_path = f / "meta.json"
            if not meta_path.is_file():
                raise ValueError(f"{meta_path}: not a crop cache (build it with recovery cache)")
            meta = json.loads(meta_path.read_text())
            if names is None:
                names = meta["keypoint_names"]
            elif meta["keypoint_names"] != names:
                raise ValueError(f"{meta_path}: keypoint_names differ from {self.folders[0]}'s")
            with np.load(f / "labels.npz") as z:
                labels = {k: z[k] for k in z.files}
            self.parts.append({"folder": f, "meta": meta, "labels": labels, "n": int(meta["count"])})
        self.keypoint_names: list[str] = list(names or [])
        self.side = int(self.parts[0]["meta"]["side"])
        self.context = float(self.parts[0]["meta"]["context"])
        if any(int(p["meta"]["side"]) != self.side for p in self.parts):
            raise ValueError("caches of different crop sizes cannot be combined")
        self.offsets = np.cumsum([0] + [p["n"] for p in self.parts])
        self._arrays: list[dict[str, np.ndarray]] | None = None

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def _open(self) -> list[dict[str, np.ndarray]]:
        if self._arrays is None:
            self._arrays = [{k: np.load(p["folder"] / f"{k}.npy", mmap_mode="r") for k in ("images", "masks", "parts")}
                            for p in self.parts]
        return self._arrays

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_arrays": None}

    def locate(self, i: int) -> tuple[int, int]:
        d = int(np.searchsorted(self.offsets, i, side="right") - 1)
        return d, i - int(self.offsets[d])

    def label(self, name: str) -> np.ndarray:
        """One label of every item, concatenated over the caches (e.g. ``"pose"`` (N, 47))."""
        return np.concatenate([p["labels"][name] for p in self.parts])

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, Any]:
        epoch, i = key if isinstance(key, tuple) else (0, key)
        d, j = self.locate(int(i))
        arr, lab = self._open()[d], self.parts[d]["labels"]
        item = {n: torch.from_numpy(np.array(arr[n][j])) for n in ("images", "masks", "parts")}
        for n in ("keypoints_2d", "keypoints_3d", "pose", "angles", "bone", "shape", "global_orient", "transl_cam", "K_crop"):
            item[n] = torch.from_numpy(np.asarray(lab[n][j], np.float32))
        item["key"] = torch.tensor([epoch, i, d, int(lab["index"][j]), int(lab["person"][j])])
        return item


class ResumableSampler(torch.utils.data.Sampler):
    """Keys ``(epoch, i)`` of a seeded permutation per epoch, from item ``start`` of epoch ``epoch``."""

    def __init__(self, n: int, seed: int, epoch: int = 0, start: int = 0, shuffle: bool = True) -> None:
        self.n, self.seed, self.epoch, self.start, self.shuffle = n, seed, epoch, start, shuffle

    def order(self, epoch: int) -> np.ndarray:
        if not self.shuffle:
            return np.arange(self.n)
        return np.random.default_rng([self.seed, epoch]).permutation(self.n)

    def __iter__(self) -> Iterator[tuple[int, int]]:
        epoch, start = self.epoch, self.start
        while True:
            for i in self.order(epoch)[start:]:
                yield epoch, int(i)
            epoch, start = epoch + 1, 0

    def __len__(self) -> int:  # endless; the trainer counts steps
        return 2**62


class ShardedBatches(torch.utils.data.Sampler):
    """One process' part of each batch of a global order (a ``batch_sampler``).

    Global batch ``s`` holds keys ``s B .. s B + B - 1`` of ``sampler`` (B = ``batch_size``, the
    global batch); rank ``r`` of ``W`` processes takes its contiguous ``B / W`` of them. So the
    ranks' parts of step ``s`` together are the single-process batch of step ``s``, in order, for any
    ``W`` dividing ``B``; with ``W = 1`` these are ``DataLoader(batch_size=B, sampler=sampler)``'s
    batches.
    """

    def __init__(self, sampler: torch.utils.data.Sampler, batch_size: int, rank: int = 0,
                 world_size: int = 1) -> None:
        if batch_size % world_size:
            raise ValueError(f"train.batch_size {batch_size} (the global batch) must be divisible by the "
                             f"{world_size} processes")
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} outside 0 .. {world_size - 1}")
        self.sampler, self.batch_size, self.rank, self.world_size = sampler, batch_size, rank, world_size

    def __iter__(self) -> Iterator[list[Any]]:
        part = self.batch_size // self.world_size
        keys = iter(self.sampler)
        while True:
            batch = list(itertools.islice(keys, self.batch_size))
            if len(batch) < self.batch_size:
                return
            yield batch[self.rank * part : (self.rank + 1) * part]

    def __len__(self) -> int:
        return len(self.sampler) // self.batch_size


class BatchAugment:
    """``collate_fn``: stack cache items and crop them to ``crop`` with seeded augmentation.

    Args:
        crop: output side, pixels.
        context: the caches' field of view over the crop's.
        augment: the augmentation (None: the plain centred crop).
        seed: the run's seed (item ``i`` of epoch ``e`` draws from ``(seed, e, i)``).
        dof_mirror: the model's ``(perm, sign)`` for flips.
        keypoint_names: the caches' keypoint names (for the left/right swap).
    """

    def __init__(self, crop: int, context: float, augment: AugmentConfig | None, seed: int,
                 dof_mirror: tuple[torch.Tensor, torch.Tensor], keypoint_names: Sequence[str],
                 effects: Any = None) -> None:
        self.crop, self.context, self.augment, self.seed = crop, context, augment, seed
        self.effects = effects if effects is not None and effects.active else None
        self.dof_perm, self.dof_sign = dof_mirror[0].clone(), dof_mirror[1].clone().float()
        names = list(keypoint_names)
        self.kp_perm = torch.tensor([names.index(mirror_name(n)) for n in names])
        self.part_swap = torch.tensor([0] + [1 + fmt.PART_NAMES.index(mirror_name(n)) for n in fmt.PART_NAMES])

    def params(self, epoch: int, i: int) -> CropParams:
        p = draw_params(self.augment, np.random.default_rng([self.seed, epoch, i]))
        e = self.effects
        if e is not None and e.truncation_prob > 0:  # its own stream: (seed, epoch, item, 2)
            u = np.random.default_rng([self.seed, epoch, i, 2]).uniform(size=2)
            if u[0] < e.truncation_prob:
                f = e.truncation_scale + (0.9 - e.truncation_scale) * u[1]
                # the side times f with the top edge kept: the centre moves up by (1 - f) / 2 of the
                # old side, i.e. (1 - f) / (2 f) of the new one (shifts are in units of the crop side)
                p = dataclasses.replace(p, scale=p.scale * f, shift=(p.shift[0], p.shift[1] - (1 - f) / (2 * f)))
        return p

    def __call__(self, items: list[dict[str, Any]]) -> dict[str, torch.Tensor]:
        b = _stack(items)
        out = self.apply(b, [self.params(int(k[0]), int(k[1])) for k in b["key"]])
        if self.effects is not None:  # their own stream: (seed, epoch, item, 1)
            rngs = [np.random.default_rng([self.seed, int(k[0]), int(k[1]), 1]) for k in b["key"]]
            out["image"] = apply_effects(out["image"], self.effects, rngs)
        return out

    def apply(self, b: dict[str, torch.Tensor], params: Sequence[CropParams]) -> dict[str, torch.Tensor]:
        """Crop the stacked cache items ``b`` with one :class:`CropParams` per item."""
        side = b["images"].shape[-2]
        view = side / self.context  # the un-augmented crop's side in cache pixels
        a2, lm = [], []
        for p in params:
            centre = (side / 2 + p.shift[0] * view * p.scale, side / 2 + p.shift[1] * view * p.scale)
            a2.append(crop_affine(centre, view * p.scale, self.crop, p.rotation_deg, p.flip))
            lm.append(camera_rotation(p.rotation_deg, p.flip))
        A = torch.tensor(np.stack(a2), dtype=torch.float32)  # (B, 3, 3)
        L = torch.tensor(np.stack(lm), dtype=torch.float32)
        flip = torch.tensor([p.flip for p in params])
        # Half-pixel conjugation: kornia (align_corners=True) puts pixel centres at integers.
        half = torch.tensor([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
        m = torch.linalg.inv(half) @ A @ half
        img = b["images"].permute(0, 3, 1, 2).float() / 255.0
        img = warp_affine(img, m[:, :2], (self.crop, self.crop), mode="bilinear", align_corners=True)
        img = _colour(img, params)
        lab = torch.stack([b["masks"].float(), b["parts"].float()], 1)
        lab = warp_affine(lab, m[:, :2], (self.crop, self.crop), mode="nearest", align_corners=True).round().long()
        mask, parts = lab[:, 0] > 0, lab[:, 1]

        kp2 = b["keypoints_2d"]
        uv = kp2[..., :2] @ A[:, :2, :2].transpose(1, 2) + A[:, None, :2, 2]
        vis = (kp2[..., 2] > 0) & (uv >= 0).all(-1) & (uv < self.crop).all(-1)
        kp3 = b["keypoints_3d"] @ L.transpose(1, 2)
        mirror = torch.diag_embed(torch.stack([torch.where(flip, -1.0, 1.0), torch.ones(len(flip)), torch.ones(len(flip))], -1))
        orient = L @ axis_angle_to_rotation_matrix(b["global_orient"]) @ mirror
        pose, angles = b["pose"].clone(), b["angles"].clone()
        if flip.any():
            f = flip
            uv[f], vis[f], kp3[f] = uv[f][:, self.kp_perm], vis[f][:, self.kp_perm], kp3[f][:, self.kp_perm]
            parts[f] = self.part_swap[parts[f]]
            pose[f] = pose[f][:, self.dof_perm] * self.dof_sign
            angles[f] = angles[f][:, self.dof_perm] * self.dof_sign
        return {
            "image": img,
            "keypoints_2d": torch.cat([uv, vis.float()[..., None]], -1),
            "keypoints_3d": kp3,
            "pose": pose,
            "angles": angles,
            "bone": b["bone"],
            "shape": b["shape"],
            "global_orient": orient,
            "transl_cam": (L @ b["transl_cam"][..., None])[..., 0],
            "K_crop": A @ b["K_crop"] @ L.transpose(1, 2),
            "mask": mask,
            "parts": parts,
            "key": b["key"],
        }


def _colour(img: torch.Tensor, params: Sequence[CropParams]) -> torch.Tensor:
    """SPIN's per-channel gains, then kornia's brightness, contrast, saturation and hue per item."""
    from kornia import enhance

    gains = torch.tensor([p.color for p in params], dtype=img.dtype)[:, :, None, None]
    x = (img * gains).clamp(0.0, 1.0)
    jit = torch.tensor([p.jitter for p in params], dtype=img.dtype)  # (B, 4)
    if (jit[:, 0] != 0).any():
        x = enhance.adjust_brightness(x, jit[:, 0])
    if (jit[:, 1] != 1).any():
        x = enhance.adjust_contrast(x, jit[:, 1])
    if (jit[:, 2] != 1).any():
        x = enhance.adjust_saturation(x, jit[:, 2])
    if (jit[:, 3] != 0).any():
        x = enhance.adjust_hue(x, jit[:, 3])
    return x.clamp(0.0, 1.0)


def apply_effects(img: torch.Tensor, spec: Any, rngs: Sequence[np.random.Generator]) -> torch.Tensor:
    """Camera, sensor and occlusion effects (:class:`recovery.config.EffectsSpec`) on (B, 3, S, S)
    crops in [0, 1], in the order light takes: an occluder in the scene, the lens' or the motion's
    blur, a lower resolution, sensor noise, then JPEG. ``rngs``: one generator per item."""
    import io

    import torch.nn.functional as F
    from kornia.filters import gaussian_blur2d, motion_blur
    from PIL import Image

    out = img.clone()
    h, w = out.shape[-2:]
    for i, rng in enumerate(rngs):
        u = rng.uniform(size=12)
        x = out[i:i + 1]
        if u[0] < spec.occlusion_prob:
            side = (0.2 + (spec.occlusion_size - 0.2) * u[1:3]) * np.array([w, h])
            ow, oh = max(int(side[0]), 1), max(int(side[1]), 1)
            dx, dy = int(u[3] * (w - ow + 1)), int(u[4] * (h - oh + 1))
            sx, sy = int(u[5] * (w - ow + 1)), int(u[6] * (h - oh + 1))
            x[0, :, dy:dy + oh, dx:dx + ow] = img[i, :, sy:sy + oh, sx:sx + ow]  # a textured object
        if u[7] < spec.blur_prob:
            if u[8] < 0.5:
                sigma = 0.5 + (spec.blur_px - 0.5) * rng.uniform()
                k = 2 * int(math.ceil(3 * sigma)) + 1
                x = gaussian_blur2d(x, (k, k), torch.tensor([[sigma, sigma]], dtype=x.dtype))
            else:
                k = 2 * int(round(rng.uniform(0.5, spec.blur_px + 0.5))) + 1
                x = motion_blur(x, k, float(rng.uniform(0, 180)), float(rng.uniform(-1, 1)))
        if u[9] < spec.lowres_prob:
            f = 1 + (spec.lowres - 1) * rng.uniform()
            small = F.interpolate(x, size=(max(int(h / f), 4), max(int(w / f), 4)), mode="area")
            x = F.interpolate(small, size=(h, w), mode="bilinear", align_corners=False)
        if spec.noise > 0:
            sigma = spec.noise * u[10]
            z = torch.from_numpy(rng.standard_normal(x.shape).astype(np.float32)).to(x.dtype)
            x = x + sigma * torch.sqrt(0.25 + x.clamp(0, 1)) * z
        x = x.clamp(0.0, 1.0)
        if u[11] < spec.jpeg_prob:
            q = int(rng.integers(spec.jpeg_quality, 96))
            arr = (x[0].permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)
            buf = io.BytesIO()
            Image.fromarray(arr).save(buf, format="JPEG", quality=q)
            buf.seek(0)
            with Image.open(buf) as im:
                x = torch.from_numpy(np.asarray(im.convert("RGB"), np.float32) / 255.0).permute(2, 0, 1)[None].to(x.dtype)
        out[i] = x[0]
    return out


def augment_config(spec: Any) -> AugmentConfig | None:
    """:class:`recovery.config.AugmentSpec` (or None) -> :class:`synth.data.AugmentConfig`."""
    if spec is None:
        return None
    from dataclasses import asdict

    return AugmentConfig(**asdict(spec))


@dataclass
class RealPoses:
    """The discriminator's real poses: angles (N, 47) from prior samples and library frames,
    drawn once; batches are drawn with a generator the trainer checkpoints."""

    angles: torch.Tensor
    sources: dict[str, int]

    def sample(self, n: int, generator: torch.Generator) -> torch.Tensor:
        idx = torch.randint(0, self.angles.shape[0], (n,), generator=generator)
        return self.angles[idx]


def real_poses(body: torch.nn.Module, prior_path: str, prior_samples: int, library: str,
               exclude_clips: Sequence[str], seed: int) -> RealPoses:
    """Real poses for the 47-D discriminator: never the training images' own labels.

    Args:
        body: the BLSM model (its Eq. 6 maps unconstrained values to angles).
        prior_path: pose prior file ("" for the packaged one).
        prior_samples: how many poses to draw from the prior.
        library: motion library folder ("" for none); clips in ``exclude_clips`` are left out.
        seed: seed of the prior draws.
    """
    from blsm.joint_limits import angles_from_unconstrained
    from blsm.mocap.prior import DEFAULT_PRIOR, load_prior

    chunks, sources = [], {}
    if prior_samples:
        prior = load_prior(prior_path or DEFAULT_PRIOR)
        x = prior.sample(prior_samples, torch.Generator().manual_seed(seed)).float()
        chunks.append(x)
        sources["prior"] = int(x.shape[0])
    if library:
        from blsm.mocap.library import list_clips, load_clip

        n = 0
        for f in list_clips(library):
            if f.stem in exclude_clips:
                continue
            clip = load_clip(f)
            chunks.append(torch.as_tensor(clip.pose, dtype=torch.float32))
            n += clip.num_frames
        sources["library"] = n
    if not chunks:
        raise ValueError("discriminator: no real poses (prior_samples is 0 and no library)")
    x = torch.cat(chunks)
    with torch.no_grad():
        angles = angles_from_unconstrained(x, body.dof_limits.float())
    return RealPoses(angles=angles, sources=sources)


def spread_indices(n: int, k: int) -> np.ndarray:
    """``k`` indices spread evenly over ``range(n)`` (all when ``k`` is 0 or >= n)."""
    if k <= 0 or k >= n:
        return np.arange(n)
    return np.unique(np.floor(np.arange(k) * (n / k)).astype(np.int64))
