"""Per-batch augmentation of cache crops (in the loader worker) and the camera, sensor and occlusion
effects.

The geometry is that of :meth:`synth.dataset.images.SynthDataset.get`: a second affine map ``A2`` from cache
to crop pixels (scale, in-plane rotation, flip, translation; pixel centres at integer + 0.5), the
camera-frame map ``L = M Rz``, so ``keypoints_3d <- L keypoints_3d``, ``transl <- L transl``,
``R_global <- L R_global M`` and ``K <- A2 K L^T``; a flip swaps left and right keypoints and parts
and mirrors the 47 atoms with the model's ``dof_mirror``. So ``K (keypoints_3d + transl)`` projects
onto ``keypoints_2d`` exactly after augmentation too. Each item's augmentation is a function of
``(seed, epoch, item)`` only (:mod:`recovery.datasets.sampling`).

The random draw of one item (:func:`draw_params`, SPIN's ranges of :class:`recovery.config.AugmentConfig`)
and its colour (:func:`color_jitter`) are also offered on the dataset's own items, one person at a
time, by :class:`AugmentedDataset`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from kornia.geometry.transform import warp_affine

from blsm.skeleton import mirror_name
from recovery.config import AugmentConfig
from recovery.datasets.cache import stack_items
from synth.dataset import format as fmt
from synth.dataset.crops import camera_rotation, crop_affine
from synth.dataset.images import SeededDataset, SynthDataset


@dataclass(frozen=True)
class CropParams:
    """The augmentation of one item: scale factor, rotation (degrees, counter-clockwise on screen),
    flip, centre shift (fraction of the side), per-channel colour factors and the kornia colour
    jitter ``(brightness added, contrast factor, saturation factor, hue shift in radians)``."""

    scale: float = 1.0
    rotation_deg: float = 0.0
    flip: bool = False
    shift: tuple[float, float] = (0.0, 0.0)
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    jitter: tuple[float, float, float, float] = (0.0, 1.0, 1.0, 0.0)


def draw_params(cfg: AugmentConfig | None, rng: np.random.Generator) -> CropParams:
    """Draw one item's :class:`CropParams` (identity without ``cfg``)."""
    if cfg is None:
        return CropParams()
    u = rng.uniform(size=9)
    sym = (2 * u - 1).tolist()  # uniform in [-1, 1]
    j = (2 * rng.uniform(size=4) - 1).tolist()
    return CropParams(
        scale=1 + sym[0] * cfg.scale,
        rotation_deg=sym[1] * cfg.rotation_deg if u[2] < cfg.rotation_prob else 0.0,
        flip=bool(u[3] < cfg.flip_prob),
        shift=(sym[4] * cfg.translation, sym[5] * cfg.translation),
        color=(1 + sym[6] * cfg.color, 1 + sym[7] * cfg.color, 1 + sym[8] * cfg.color),
        jitter=(j[0] * cfg.brightness, 1 + j[1] * cfg.contrast, 1 + j[2] * cfg.saturation, j[3] * cfg.hue * 2 * math.pi),
    )


def color_jitter(image: torch.Tensor, jitter: tuple[float, float, float, float]) -> torch.Tensor:
    """Brightness, contrast, saturation and hue of a (3, H, W) image in [0, 1] with kornia, in that
    order; the identity ``(0, 1, 1, 0)`` returns the image unchanged."""
    from kornia import enhance

    b, c, s, h = jitter
    x = image[None]
    if b != 0.0:
        x = enhance.adjust_brightness(x, b)
    if c != 1.0:
        x = enhance.adjust_contrast(x, c)
    if s != 1.0:
        x = enhance.adjust_saturation(x, s)
    if h != 0.0:
        x = enhance.adjust_hue(x, h)
    return x[0].clamp(0.0, 1.0)


class AugmentedDataset(SeededDataset):
    """SPIN-style random crops of a :class:`synth.dataset.images.SynthDataset`'s items: per item one
    :func:`draw_params` draw (scale, rotation, flip, shift: the reader's exact crop geometry, labels
    included), then the per-channel gains and :func:`color_jitter`.

        ds = AugmentedDataset(SynthDataset("data/train", crop=224), AugmentConfig(), seed=0)

    Args:
        dataset: the reader (its ``crop``, ``person``, ``keypoints`` and filters apply).
        augment: the ranges.
        seed: None: fresh draws every call (torch's RNG, seeded per DataLoader worker); an int:
            item ``i`` in epoch ``e`` (:meth:`set_epoch`) is a function of ``(seed, e, i)``.
    """

    def __init__(self, dataset: SynthDataset, augment: AugmentConfig | None = None, seed: int | None = None) -> None:
        self.dataset, self.augment = dataset, augment if augment is not None else AugmentConfig()
        self.items, self.seed, self.epoch = dataset.items, seed, 0
        self.keypoint_names = dataset.keypoint_names

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        p = draw_params(self.augment, self.item_rng(i))
        item = self.dataset.get(i, scale=p.scale, rotation_deg=p.rotation_deg, flip=p.flip, shift=p.shift)
        item["image"] = colour(item["image"][None], [p])[0]
        return item



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
        fda = self.effects is not None and self.effects.fda_prob > 0  # FDA's photographs, read once
        self._photos = read_photos(self.effects.fda_folder, 2 * crop) if fda else None
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
        b = stack_items(items)
        out = self.apply(b, [self.params(int(k[0]), int(k[1])) for k in b["key"]])
        if self.effects is not None and self.effects.styled:  # their own stream: (seed, epoch, item, 3)
            rngs = [np.random.default_rng([self.seed, int(k[0]), int(k[1]), 3]) for k in b["key"]]
            out["image"] = apply_style(out["image"], self.effects, rngs, self._photos)
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
        img = colour(img, params)
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


def colour(img: torch.Tensor, params: Sequence[CropParams]) -> torch.Tensor:
    """SPIN's per-channel gains, then :func:`color_jitter` per item (brightness, contrast, saturation,
    hue), on (B, 3, S, S) crops in [0, 1]."""
    gains = torch.tensor([p.color for p in params], dtype=img.dtype)[:, :, None, None]
    x = (img * gains).clamp(0.0, 1.0)
    return torch.stack([color_jitter(x[i], p.jitter) for i, p in enumerate(params)])


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


PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")


def read_photos(folder: str, side: int) -> list[np.ndarray]:
    """The photographs of ``folder`` (sorted by name), each scaled so that its shorter side is
    ``side`` pixels, as (H, W, 3) uint8 arrays. A missing folder or one without photographs is a
    ValueError naming it."""
    from PIL import Image

    path = Path(folder).expanduser()
    files = sorted(p for p in path.glob("*") if p.suffix.lower() in PHOTO_SUFFIXES) if path.is_dir() else []
    if not files:
        raise ValueError(f"{path}: data.effects.fda_folder holds no photographs (.jpg, .jpeg, .png)")
    out = []
    for f in files:
        with Image.open(f) as im:
            im = im.convert("RGB")
            s = side / min(im.size)
            out.append(np.asarray(im.resize((max(round(im.width * s), side), max(round(im.height * s), side)),
                                            Image.Resampling.BILINEAR)))
    return out


def random_convolution(x: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
    """RandConv (Xu et al., ICLR 2021) on one (1, 3, S, S) crop: a random 3 -> 3 convolution of size
    k in {1, 3, 5, 7}, weights N(0, 1 / (3 k^2)), reflect padding; its output matched to the crop's
    per-channel mean and deviation, mixed with the crop by a uniform ``a``."""
    import torch.nn.functional as F

    k = int(rng.choice([1, 3, 5, 7]))
    w = torch.from_numpy(rng.normal(0.0, 1.0 / math.sqrt(3 * k * k), size=(3, 3, k, k)).astype(np.float32)).to(x.dtype)
    y = F.conv2d(F.pad(x, (k // 2,) * 4, mode="reflect") if k > 1 else x, w)
    mx, sx = x.mean((2, 3), keepdim=True), x.std((2, 3), keepdim=True)
    y = (y - y.mean((2, 3), keepdim=True)) / (y.std((2, 3), keepdim=True) + 1e-6) * sx + mx
    a = float(rng.uniform())
    return (a * x + (1 - a) * y).clamp(0.0, 1.0)


def fourier_style(x: torch.Tensor, photo: np.ndarray, beta: float, rng: np.random.Generator) -> torch.Tensor:
    """FDA (Yang and Soatto, CVPR 2020) on one (1, 3, S, S) crop: the amplitude of its lowest
    frequencies (a centred square of half-side b, b uniform in 1..max(1, floor(beta S))) replaced by
    that of a random square of ``photo`` (H, W, 3) uint8 scaled to S; the phase kept."""
    import torch.nn.functional as F

    s = x.shape[-1]
    h, w = photo.shape[:2]
    side = int(rng.integers(min(h, w) // 2, min(h, w) + 1))
    y0, x0 = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
    t = torch.from_numpy(np.ascontiguousarray(photo[y0:y0 + side, x0:x0 + side])).permute(2, 0, 1)[None].to(x.dtype) / 255.0
    t = F.interpolate(t, size=(s, s), mode="area")
    b = int(rng.integers(1, max(1, int(beta * s)) + 1))
    fx = torch.fft.fftshift(torch.fft.fft2(x), dim=(-2, -1))
    ft = torch.fft.fftshift(torch.fft.fft2(t), dim=(-2, -1))
    amp, phase = fx.abs(), fx.angle()
    c = s // 2
    amp[..., c - b:c + b + 1, c - b:c + b + 1] = ft.abs()[..., c - b:c + b + 1, c - b:c + b + 1]
    y = torch.fft.ifft2(torch.fft.ifftshift(torch.polar(amp, phase), dim=(-2, -1))).real
    return y.clamp(0.0, 1.0)


def apply_style(img: torch.Tensor, spec: Any, rngs: Sequence[np.random.Generator],
                photos: Sequence[np.ndarray] | None) -> torch.Tensor:
    """The style effects of :class:`recovery.config.EffectsSpec` on (B, 3, S, S) crops in [0, 1]:
    RandConv, then FDA towards a real photograph. ``rngs``: one generator per item."""
    out = img.clone()
    for i, rng in enumerate(rngs):
        u = rng.uniform(size=3)
        x = out[i:i + 1]
        if u[0] < spec.randconv_prob:
            x = random_convolution(x, rng)
        if u[1] < spec.fda_prob:
            if not photos:
                raise ValueError("FDA needs photographs (read_photos of data.effects.fda_folder)")
            x = fourier_style(x, photos[int(u[2] * len(photos))], spec.fda_beta, rng)
        out[i] = x[0]
    return out
