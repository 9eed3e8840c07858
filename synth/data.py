"""A PyTorch dataset of person crops from a generated dataset folder, HMR/SPIN style.

    ds = SynthDataset("data/train", crop=224, augment=AugmentConfig(), seed=None)
    loader = DataLoader(ds, batch_size=64, num_workers=8, shuffle=True)

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

Items (float32 unless stated): ``image`` (3, crop, crop) in [0, 1] (ImageNet-normalised with
``normalize=True``), ``keypoints_2d`` (K, 3) crop pixels and visibility (visible in the image and
inside the crop), ``keypoints_3d`` (K, 3) camera metres relative to the pelvis, ``pose`` (47,),
``angles`` (47,) radians, ``bone`` (Kb,), ``shape`` (Ks,), ``global_orient`` (3,) camera-frame
axis-angle, ``transl_cam`` (3,) metres, ``K_crop`` (3, 3), ``affine`` (3, 3) the map ``A``,
``mask`` (crop, crop) bool, ``parts`` (crop, crop) int64 (0 background, 1 + ``PART_NAMES`` index),
``index`` (sample index) and ``person`` (int64).
"""

from __future__ import annotations

import functools
import math
import os
import tarfile
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle
from kornia.geometry.transform import warp_affine

from blsm.io import sha256_file
from blsm.skeleton import mirror_name
from synth import format as fmt
from synth.shards import FORMAT as SHARDS_FORMAT
from synth.shards import MANIFEST

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
MEAN_CHW, STD_CHW = torch.tensor(IMAGENET_MEAN).view(3, 1, 1), torch.tensor(IMAGENET_STD).view(3, 1, 1)
_FIELDS = ("json", "rgb.png", "mask.png", "parts.png")
_PART_SWAP = torch.tensor([0] + [1 + fmt.PART_NAMES.index(mirror_name(n)) for n in fmt.PART_NAMES])


@dataclass(frozen=True)
class AugmentConfig:
    """Random crop augmentation (defaults after SPIN / HMR).

    Attributes:
        scale: the crop side is multiplied by a factor uniform in ``[1 - scale, 1 + scale]``.
        rotation_deg: in-plane rotation uniform in ``[-rotation_deg, rotation_deg]`` degrees ...
        rotation_prob: ... drawn with this probability (else 0).
        flip_prob: probability of a horizontal mirror.
        color: per-channel multiplicative colour factor uniform in ``[1 - color, 1 + color]``
            (SPIN's channel noise).
        translation: crop centre shift, uniform in ``[-translation, translation]`` times the side.
        brightness: added brightness uniform in ``[-brightness, brightness]``
            (``kornia.enhance.adjust_brightness``).
        contrast: contrast factor uniform in ``[1 - contrast, 1 + contrast]`` (``adjust_contrast``).
        saturation: saturation factor uniform in ``[1 - saturation, 1 + saturation]``
            (``adjust_saturation``).
        hue: hue shift uniform in ``[-hue, hue]`` turns (``adjust_hue``, which takes radians).
    """

    scale: float = 0.25
    rotation_deg: float = 30.0
    rotation_prob: float = 0.6
    flip_prob: float = 0.5
    color: float = 0.4
    translation: float = 0.05
    brightness: float = 0.1
    contrast: float = 0.2
    saturation: float = 0.2
    hue: float = 0.02

    def __post_init__(self) -> None:
        ok = 0 <= self.scale < 1 and 0 <= self.color < 1 and min(self.rotation_deg, self.translation) >= 0
        ok &= 0 <= self.brightness <= 1 and 0 <= self.contrast < 1 and 0 <= self.saturation < 1 and 0 <= self.hue <= 0.5
        if not (ok and 0 <= self.rotation_prob <= 1 and 0 <= self.flip_prob <= 1):
            raise ValueError(
                f"augment ranges must be >= 0 (scale, color, contrast, saturation < 1; brightness, "
                f"probabilities <= 1; hue <= 0.5), got {self}"
            )


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


def crop_affine(
    center: Sequence[float], side: float, crop: int, rotation_deg: float = 0.0, flip: bool = False
) -> np.ndarray:
    """The map from original to crop pixel coordinates (both with pixel centres at integer + 0.5).

    Args:
        center: (2,) crop centre in original pixels; it maps to ``(crop / 2, crop / 2)``.
        side: crop side in original pixels.
        crop: output size in pixels.
        rotation_deg: in-plane rotation of the content, counter-clockwise on screen, degrees.
        flip: mirror the crop horizontally (``x -> crop - x``).

    Returns:
        (3, 3) float64 affine matrix ``A``; a point ``p`` maps to ``A [p, 1]``.
    """
    if side <= 0 or crop < 1:
        raise ValueError(f"crop side and size must be positive, got {side}, {crop}")
    out = (crop / side) * camera_rotation(rotation_deg, False)
    out[2] = [0.0, 0.0, 1.0]
    out[:2, 2] = crop / 2 - out[:2, :2] @ np.asarray(center, dtype=np.float64)
    if flip:
        out = np.array([[-1.0, 0.0, crop], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) @ out
    return out


def map_points(points: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """(..., 2) pixel points through a (3, 3) affine (:func:`crop_affine`'s ``A``, or its inverse to go
    from crop back to original pixels): ``A [p, 1]``, without the homogeneous coordinate."""
    return points @ affine[:2, :2].T + affine[:2, 2]


def camera_rotation(rotation_deg: float, flip: bool) -> np.ndarray:
    """``L = M Rz`` (3, 3): the camera-frame map matching :func:`crop_affine`'s rotation and flip."""
    c, s = math.cos(math.radians(rotation_deg)), math.sin(math.radians(rotation_deg))
    return np.diag([-1.0 if flip else 1.0, 1.0, 1.0]) @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


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


def warp_to_crop(image: torch.Tensor, affine: np.ndarray, crop: int, mode: str = "bilinear",
                 antialias: bool = True) -> torch.Tensor:
    """Warp (C, H, W) into (C, crop, crop) with :func:`crop_affine`'s ``A``; zeros outside.

    kornia's ``warp_affine`` (``align_corners=True``) puts pixel centres at integers, so ``A`` is
    conjugated by the half-pixel shift: output pixel ``(u, v)`` samples ``A^-1 (u + .5, v + .5) - .5``.

    With ``antialias`` (bilinear only) a crop that shrinks its source by ``s > 1`` source pixels per
    crop pixel is low-pass filtered first (:func:`prefilter_for_crop`): bilinear sampling alone reads
    4 of every ``s^2`` source pixels, so a person photographed at 800 px and seen at 128 px would
    arrive aliased, a look no rendered training crop has.
    """
    if antialias and mode == "bilinear":
        image, affine = prefilter_for_crop(image, affine, crop)
    half = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    m = np.linalg.inv(half) @ affine @ half
    mt = torch.as_tensor(m[None, :2], dtype=image.dtype)
    return warp_affine(image[None], mt, (crop, crop), mode=mode, align_corners=True)[0]


def crop_shrink(affine: np.ndarray) -> float:
    """Source pixels per crop pixel of a similarity ``A`` (:func:`crop_affine`): ``|det A|^-1/2``."""
    return float(abs(np.linalg.det(np.asarray(affine, np.float64)[:2, :2])) ** -0.5)


def prefilter_for_crop(image: torch.Tensor, affine: np.ndarray, crop: int) -> tuple[torch.Tensor, np.ndarray]:
    """The source region a crop reads, low-pass filtered for its shrink ``s`` (:func:`crop_shrink`),
    and the affine from that region's pixels to the crop's. Identity where ``s <= 1``.

    The region is the crop's footprint plus a margin, cut from the image (what lies outside the
    image stays outside: the warp fills it with zeros). Then, as an image pyramid does, it is
    averaged over ``k x k`` blocks for the integer part ``k = floor(s)`` (area resampling; the
    block ``i`` covers source pixels ``[k i, k i + k)``, centre ``k (i + 1/2)``, so the affine gains
    ``diag(k, k, 1)``), and the remaining shrink ``r = s / k`` in ``[1, 2)`` is covered by a
    Gaussian of ``sigma = (r - 1) / 2`` (scikit-image's ``resize`` anti-aliasing rule).

    Args:
        image: (C, H, W) float.
        affine: (3, 3) source -> crop pixel coordinates (pixel centres at integer + 0.5).
        crop: crop side in pixels.
    """
    from kornia.filters import gaussian_blur2d

    affine = np.asarray(affine, np.float64)
    s = crop_shrink(affine)
    if not s > 1.0 + 1e-6:
        return image, affine
    h, w = image.shape[-2:]
    inv = np.linalg.inv(affine)
    corners = np.array([[0, 0, 1], [crop, 0, 1], [0, crop, 1], [crop, crop, 1]], np.float64) @ inv.T
    margin = 3.0 * s + 2.0
    k = int(math.floor(s))
    # the region starts on the block grid of the whole image, so two crops of one image at one
    # shrink see the same blocks wherever they lie (the cache's crop and the dataset's agree)
    x0 = int(np.clip(np.floor(corners[:, 0].min() - margin), 0, w)) // k * k
    x1 = int(np.clip(np.ceil(corners[:, 0].max() + margin), 0, w))
    y0 = int(np.clip(np.floor(corners[:, 1].min() - margin), 0, h)) // k * k
    y1 = int(np.clip(np.ceil(corners[:, 1].max() + margin), 0, h))
    if x1 - x0 < 1 or y1 - y0 < 1:  # the crop sees none of the image: zeros either way
        return image, affine
    region = image[..., y0:y1, x0:x1]
    shift = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])
    affine = affine @ shift
    if k >= 2:
        rh, rw = region.shape[-2:]
        ph, pw = -rh % k, -rw % k  # the last block is filled by repeating the edge (under one block)
        if ph or pw:
            region = torch.nn.functional.pad(region[None], (0, pw, 0, ph), mode="replicate")[0]
        region = torch.nn.functional.avg_pool2d(region[None], k)[0]
        affine = affine @ np.diag([float(k), float(k), 1.0])
        s = s / k
    sigma = (s - 1.0) / 2.0
    if sigma > 0.05:
        size = 2 * int(math.ceil(3.0 * sigma)) + 1
        region = gaussian_blur2d(region[None], (size, size), (sigma, sigma), border_type="replicate")[0]
    return region, affine


class DatasetIndex:
    """The samples of a dataset folder and the byte ranges of their tar members.

    Built from ``manifest.json`` and the shards' tar headers; :meth:`read` then reads one member with
    one seek. File handles are opened lazily per process, so the index survives ``fork`` (DataLoader
    workers) and pickling.

    Raises:
        ValueError: one line naming the file, on a missing folder or manifest, a manifest of another
            format, an incomplete run (unless ``allow_incomplete``), a missing or truncated shard, a
            shard whose SHA-256 differs from the manifest's (with ``verify``; it reads every byte), or
            a sample without the ``required`` members.
    """

    def __init__(self, path: str | Path, allow_incomplete: bool = False, required: Sequence[str] = _FIELDS,
                 verify: bool = False):
        self.root, self.required = Path(path), tuple(required)
        man_path = self.root / MANIFEST
        if not man_path.is_file():
            raise ValueError(f"{man_path}: no dataset manifest here")
        try:
            man = fmt.decode_json(man_path.read_bytes(), str(man_path))
        except OSError as exc:
            raise ValueError(f"{man_path}: unreadable ({exc.strerror})") from None
        if not isinstance(man, dict) or man.get("format") != SHARDS_FORMAT:
            raise ValueError(f"{man_path}: not a {SHARDS_FORMAT!r} manifest")
        if not man.get("complete") and not allow_incomplete:
            raise ValueError(f"{man_path}: the dataset is incomplete (generation unfinished)")
        shards = man.get("shards") or {}
        if not isinstance(shards, dict) or not all(
            isinstance(e, dict) and isinstance(e.get("samples", -1), int) for e in shards.values()
        ):
            raise ValueError(f"{man_path}: 'shards' must map each shard's name to its entry")
        self.shards: list[Path] = []
        self.samples: list[tuple[int, str, dict[str, tuple[int, int]]]] = []
        for name, entry in sorted(shards.items()):
            path = self.root / name
            if verify and path.is_file() and sha256_file(path) != entry.get("sha256"):
                raise ValueError(f"{path}: SHA-256 differs from the manifest (damaged or edited)")
            self._index_shard(len(self.shards), path, int(entry.get("samples", -1)))
        self._pid = -1
        self._files: dict[int, BinaryIO] = {}

    def _index_shard(self, s: int, path: Path, expected: int) -> None:
        if not path.is_file():
            raise ValueError(f"{path}: shard listed in the manifest is missing")
        size = path.stat().st_size
        members: dict[str, dict[str, tuple[int, int]]] = {}
        try:
            with tarfile.open(path, mode="r:") as tar:
                for m in tar:
                    if m.isfile():
                        if m.offset_data + m.size > size:
                            raise ValueError(f"{path}: truncated shard (member {m.name} ends past the file)")
                        key, _, name = m.name.partition(".")
                        members.setdefault(key, {})[name] = (m.offset_data, m.size)
        except (OSError, tarfile.TarError) as exc:
            raise ValueError(f"{path}: not a readable shard ({exc})") from None
        if expected >= 0 and len(members) != expected:
            raise ValueError(f"{path}: holds {len(members)} samples, the manifest says {expected}")
        for key, fields in members.items():
            missing = [f for f in self.required if f not in fields]
            if missing:
                raise ValueError(f"{path}: sample {key} lacks {missing} (truncated or not a synth dataset)")
        self.shards.append(path)
        self.samples.extend((s, key, fields) for key, fields in members.items())

    def __len__(self) -> int:
        return len(self.samples)

    def where(self, i: int) -> str:
        s, key, _ = self.samples[i]
        return f"{self.shards[s]}:{key}"

    def read(self, i: int, fields: Sequence[str]) -> dict[str, bytes]:
        """The raw bytes of the given members of sample ``i`` (a ValueError names a missing one)."""
        if os.getpid() != self._pid:  # a forked worker must not share the parent's file offsets
            self._files, self._pid = {}, os.getpid()
        s, key, members = self.samples[i]
        fh = self._files.get(s)
        if fh is None:
            fh = self._files[s] = open(self.shards[s], "rb")  # kept open: one per shard per process
        out = {}
        for name in fields:
            if name not in members:
                raise ValueError(f"{self.where(i)}: sample has no {name!r} member")
            offset, size = members[name]
            fh.seek(offset)
            out[name] = fh.read(size)
            if len(out[name]) != size:
                raise ValueError(f"{self.where(i)}.{name}: truncated member")
        return out

    def json(self, i: int) -> dict[str, Any]:
        return fmt.decode_json(self.read(i, ("json",))["json"], f"{self.where(i)}.json")

    def close(self) -> None:
        """Close this process's open shard files (they reopen on the next read)."""
        if self._pid == os.getpid():
            for fh in self._files.values():
                fh.close()
        self._files = {}

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_files": {}, "_pid": -1}


def check_png_crc(data: bytes, what: str) -> None:
    """Check the CRC of every chunk of PNG bytes (a ValueError naming ``what`` on a mismatch).

    PIL does not check the image data's CRCs and stops inflating once it has every row, so a
    damaged byte there can decode, silently, into wrong pixels.
    """
    if not data.startswith(b"\x89PNG\r\n\x1a\n"):
        return  # not a PNG at all: decoding says so
    pos = 8
    while pos + 12 <= len(data):
        n = int.from_bytes(data[pos : pos + 4], "big")
        body, crc = data[pos + 4 : pos + 8 + n], data[pos + 8 + n : pos + 12 + n]
        if len(crc) < 4 or zlib.crc32(body).to_bytes(4, "big") != crc:
            chunk = body[:4].decode("latin-1")
            raise ValueError(f"{what}: not a readable PNG (bad CRC in its {chunk!r} chunk)")
        pos += 12 + n


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


class SynthDataset(SeededDataset):
    """Person crops with 2D/3D keypoints, BLSM parameters and masks (see the module docstring).

    Args:
        path: dataset folder (``manifest.json`` and ``shard-*.tar``).
        crop: output side in pixels.
        augment: random augmentation, or None for the plain centred crop.
        person: ``"all"`` (one item per person instance) or ``"largest"`` (one item per image).
        keypoints: ``"all"`` (every keypoint of the samples' ``keypoint_names``), a model keypoint
            set (``"coco17"``, ``"blsm_joints"``) or a list of names; it must be closed under the
            left/right mirror.
        box_scale: crop side over the box's longer side before augmentation (1.2 as in SPIN).
        min_pixels: skip persons with fewer visible mask pixels.
        min_visible: skip persons with fewer visible selected keypoints.
        normalize: subtract the ImageNet mean and divide by its standard deviation.
        seed: None: fresh augmentation every call (from torch's RNG, which DataLoader seeds per
            worker); an int: item ``i`` in epoch ``e`` (:meth:`set_epoch`) is a function of
            ``(seed, e, i)``.
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
        augment: AugmentConfig | None = None,
        person: str = "all",
        keypoints: str | Sequence[str] = "all",
        *,
        box_scale: float = 1.2,
        min_pixels: int = 1,
        min_visible: int = 0,
        normalize: bool = False,
        seed: int | None = None,
        allow_incomplete: bool = False,
        antialias: bool = True,
    ) -> None:
        if person not in ("all", "largest"):
            raise ValueError(f"person must be 'all' or 'largest', got {person!r}")
        if crop < 1 or box_scale <= 0:
            raise ValueError(f"crop and box_scale must be positive, got {crop}, {box_scale}")
        self.crop, self.augment, self.box_scale = int(crop), augment, float(box_scale)
        self.normalize, self.seed, self.epoch, self.antialias = normalize, seed, 0, bool(antialias)
        self.index = DatasetIndex(path, allow_incomplete)
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

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return self.get(i, draw_params(self.augment, self.item_rng(i)))

    def get(self, i: int, params: CropParams) -> dict[str, torch.Tensor]:
        """Item ``i`` with the given augmentation (``__getitem__`` draws ``params``)."""
        s, p = self.items[i]
        rgb, own, parts, lab = self._read(s, p)
        x0, y0, x1, y1 = lab["box"]
        side = max(x1 - x0, y1 - y0, 1.0) * self.box_scale * params.scale
        center = ((x0 + x1) / 2 + params.shift[0] * side, (y0 + y1) / 2 + params.shift[1] * side)
        amat = crop_affine(center, side, self.crop, params.rotation_deg, params.flip)
        lmat = camera_rotation(params.rotation_deg, params.flip)
        mirror = np.diag([-1.0 if params.flip else 1.0, 1.0, 1.0])

        image = warp_to_crop(torch.tensor(rgb).permute(2, 0, 1).float() / 255.0, amat, self.crop,
                             antialias=self.antialias)
        image = color_jitter((image * torch.tensor(params.color).view(3, 1, 1)).clamp(0.0, 1.0), params.jitter)
        if self.normalize:
            image = (image - MEAN_CHW) / STD_CHW
        labels = torch.from_numpy(np.stack([own, np.where(own, parts, 0)]).astype(np.float32))
        labels = warp_to_crop(labels, amat, self.crop, mode="nearest")
        part_map = labels[1].round().long()

        uv = map_points(lab["kp2"], amat)  # (K, 2)
        vis = lab["vis"] & (uv >= 0).all(1) & (uv < self.crop).all(1)
        pelvis = lab["kp3"][self._pelvis]
        rel = (lab["kp3"][self._sel] - pelvis) @ lmat.T  # (K, 3)
        orient = lmat @ lab["R"] @ lab["orient"] @ mirror
        pose, angles = lab["pose"], lab["angles"]
        if params.flip:
            uv, vis, rel = uv[self._kp_perm], vis[self._kp_perm], rel[self._kp_perm]
            part_map = _PART_SWAP[part_map]
            pose, angles = pose[self._dof_perm] * self._dof_sign, angles[self._dof_perm] * self._dof_sign

        def f32(x: Any) -> torch.Tensor:
            return torch.as_tensor(np.asarray(x, np.float64), dtype=torch.float32)

        return {
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

    def _read(self, s: int, p: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Sample ``s``'s image (H, W, 3), person ``p``'s mask (H, W) bool, the parts (H, W) and labels."""
        where = self.index.where(s)
        raw = self.index.read(s, _FIELDS)
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
