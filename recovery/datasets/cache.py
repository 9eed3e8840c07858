"""Pre-cropped caches of ``synth`` datasets: what training reads.

Decoding a PNG and warping it per item costs more CPU than a small network's step on two cores, so
training reads a **cache**: every person of a dataset cropped once by :class:`synth.dataset.images.SynthDataset`
(no augmentation) at ``context`` times the training crop's field of view, stored as uint8 arrays
(``images.npy`` (N, S, S, 3), ``masks.npy`` and ``parts.npy`` (N, S, S)) and the labels
(``labels.npz``), with ``meta.json`` written last. A cache is rebuilt when its dataset's manifest or
the crop settings change, and is written into a temporary folder renamed when complete. The crops
are augmented per batch by :class:`recovery.datasets.augment.BatchAugment`.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm.io import sha256_file
from recovery.config import DataConfig
from synth.dataset.images import SynthDataset
from synth.dataset.shards import MANIFEST

CACHE_FORMAT = "recovery-crop-cache"
CACHE_VERSION = 2  # 2: crops prefiltered where they shrink the image (synth.dataset.crops.warp_to_crop)
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
    ds = SynthDataset(dataset, crop=side, box_scale=box_scale)
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
    loader = torch.utils.data.DataLoader(ds, batch_size=64, num_workers=workers, collate_fn=stack_items)
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


def stack_items(items: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
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


def build_caches(data: DataConfig, log: Any = print) -> tuple[list[Path], Path | None]:
    """Build (or reuse) the caches of a config's training and validation datasets."""
    d = data
    for path in (*d.train, *([d.val] if d.val else [])):
        if not Path(path).is_dir():
            raise ValueError(f"{path}: no such dataset folder")
    train = [build_cache(p, cache_folder(p, d.cache, d.crop, d.context), d.crop, d.context, log=log) for p in d.train]
    val = build_cache(d.val, cache_folder(d.val, d.cache, d.crop, d.context), d.crop, d.context, log=log) if d.val else None
    return train, val
