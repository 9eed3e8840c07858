"""Learning the 2D landmark detector (:mod:`blsm.pose2d.landmark_net`) from textured stand-in scans.

Training data: every scan of the given populations (:mod:`blsm.learn.scans.population`, textured) is turned
about the vertical through its centre by a random angle and rendered from the registration's own
cameras (:func:`blsm.learn.markerless.multiview.view_cameras`, 18 views on the sphere zone, 448 px); the label
of a view is the projection of the scan's true landmarks (``A_lm gt_points``, Eq. 5.13, no landmark
noise) with its camera. So the detector learns exactly what the registration later asks of it, on
the same renders, and the evaluation scans (other seeds, other subjects) are never seen.

Each training sample is one view, cropped as at detection time (:func:`crop_square`) with a random
crop growth (1.1-1.45 times the box) and shift (up to 6 % of the side), mirrored left/right half
of the time (the landmarks' sides exchanged), and with random brightness, contrast and colour
gains (up to 20 %). Loss: mean-squared error against Gaussian heatmaps (sigma 1.5 cells), as
SimpleBaselines; Adam with a cosine learning rate. Part of the scans (``val_fraction``) is held out
to report the pixel error of the decoded detections per epoch.

``blsm train-landmark-detector POPULATION [...] --out FILE`` runs it; the packaged detector was
made by ``scripts/landmark_detector.py`` (docs/markerless.md).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm.pose2d.landmark_net import (
    CROP_GROWTH,
    LandmarkNet,
    crop_box,
    crop_square,
    decode_heatmaps,
    gaussian_heatmaps,
    mirror_index,
    save_detector,
)


@dataclass(frozen=True)
class DetectorTrainConfig:
    """Training of the landmark detector.

    Attributes:
        size: network input side, pixels (heatmaps are size / 4).
        epochs, batch, lr, weight_decay: optimisation (Adam, cosine decay to 1 % of ``lr``).
        sigma: heatmap Gaussian, cells.
        fg_weight: the squared error of a cell is weighted ``1 + fg_weight * target`` (the few cells
            near a landmark count more than the many empty ones; without it the network sits long
            near the all-zero output).
        coord_weight, beta: weight of the L1 error (cells) of the soft-argmax of ``softmax(beta * h)``
            against the label (integral regression, Sun et al. 2018), for labelled landmarks.
        growth_range, shift: crop augmentation (times the box side; fraction of the crop side).
        color: brightness / contrast / per-channel gain augmentation (relative).
        val_fraction: scans held out for the per-epoch validation error.
        seed: rotations, splits, augmentation and initialisation.
        init: start from this detector file's weights (None: random).
        widths: :class:`LandmarkNet` encoder channels.
    """

    size: int = 256
    epochs: int = 12
    batch: int = 16
    lr: float = 2e-3
    weight_decay: float = 1e-4
    sigma: float = 1.5
    fg_weight: float = 10.0
    coord_weight: float = 0.5
    beta: float = 30.0
    growth_range: tuple[float, float] = (1.1, 1.45)
    shift: float = 0.06
    color: float = 0.2
    val_fraction: float = 0.08
    init: str | None = None
    seed: int = 0
    widths: tuple[int, ...] = (24, 32, 64, 128, 192)


def render_scan_views(
    scan: Any, angle: float, views: Any = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The registration's renders of ``scan`` turned by ``angle`` about the vertical, with labels.

    Returns:
        (images (C, H, W, 3) uint8, boxes (C, 4) pixels, uv (C, L, 2) the true landmarks' projections).
    """
    from blsm.learn.markerless.multiview import ViewConfig, render_scan
    from blsm.learn.scans.format import landmark_points

    vcfg = ViewConfig() if views is None else views
    if getattr(scan, "gt_points", None) is None:
        raise ValueError(f"{scan.meta.get('id', 'scan')}: a training scan needs gt_points (a stand-in scan)")
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    centre = np.median(scan.vertices, axis=0)
    verts = (scan.vertices - centre) @ rot.T + centre
    truth = landmark_points(torch.as_tensor(np.asarray(scan.gt_points, np.float64))).numpy()
    truth = (truth - centre) @ rot.T + centre
    cams, boxes, images = render_scan(verts, scan.faces, scan.colors, vcfg)
    uv = np.stack([cam.project(truth) for cam in cams])
    return np.stack(images), boxes, uv


def make_training_views(
    populations: list[Path], out: Path, seed: int = 0, log: Callable[[str], None] = print, views: Any = None
) -> Path:
    """Render every scan of the populations (:func:`render_scan_views`) into one ``.npz`` (``images``,
    ``boxes``, ``uv``, ``scan`` index per view, ``ids``); skipped if ``out`` exists."""
    from blsm.io import atomic_write
    from blsm.learn.scans.format import load_scan

    if out.exists():
        return out
    files = [p for pop in populations for p in sorted((Path(pop) / "scans").glob("*.npz"))]
    if not files:
        raise ValueError(f"{populations[0]}: no scans (a population folder holds scans/*.npz)")
    rng = np.random.default_rng(seed)
    imgs, boxes, uvs, owner = [], [], [], []
    t0 = time.time()
    for i, p in enumerate(files):
        scan = load_scan(p)
        scan.meta = {**(scan.meta or {}), "id": p.stem}
        im, bx, uv = render_scan_views(scan, float(rng.uniform(0, 2 * math.pi)), views)
        imgs.append(im)
        boxes.append(bx)
        uvs.append(uv)
        owner += [i] * len(im)
        if i % 10 == 0:
            log(
                f"[detector] rendered {i + 1}/{len(files)} scans, {(time.time() - t0) / (i + 1):.1f} s per scan"
            )
    with atomic_write(out, "wb") as fh:
        np.savez(
            fh,
            images=np.concatenate(imgs),
            boxes=np.concatenate(boxes),
            uv=np.concatenate(uvs).astype(np.float32),
            scan=np.array(owner),
            ids=np.array([str(p) for p in files]),
        )
    return out


def random_objects(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A scene without a person: 1-4 random primitives (boxes, cylinders, capsules, spheres, cones) of
    0.1-1.8 m on the floor, random colours with noise. Returns (vertices, faces, colours uint8)."""
    import trimesh

    parts = []
    for _ in range(int(rng.integers(1, 5))):
        dims = rng.uniform(0.1, 1.8, 3) * (1.0 if rng.random() < 0.5 else rng.uniform(0.2, 1.0))
        kind = int(rng.integers(5))
        if kind == 0:
            m = trimesh.creation.box(extents=dims)
        elif kind == 1:
            m = trimesh.creation.cylinder(radius=dims[0] / 2, height=dims[1], sections=24)
        elif kind == 2:
            m = trimesh.creation.capsule(height=dims[1], radius=min(dims[0], dims[1]) / 4, count=[16, 16])
        elif kind == 3:
            m = trimesh.creation.icosphere(subdivisions=3, radius=dims[0] / 2)
        else:
            m = trimesh.creation.cone(radius=dims[0] / 2, height=dims[1], sections=24)
        if kind in (1, 2, 4):  # trimesh's axis is Z; stand it up (Y) or lay it down
            m.apply_transform(
                trimesh.transformations.rotation_matrix(-np.pi / 2 * (rng.random() < 0.7), [1, 0, 0])
            )
        m.apply_transform(trimesh.transformations.rotation_matrix(rng.uniform(0, 2 * np.pi), [0, 1, 0]))
        m.apply_translation([rng.uniform(-0.5, 0.5), -m.bounds[0, 1], rng.uniform(-0.5, 0.5)])
        col = np.clip(rng.uniform(30, 230, 3) + rng.normal(0, 12, (len(m.vertices), 3)), 0, 255)
        parts.append((np.asarray(m.vertices), np.asarray(m.faces), col.astype(np.uint8)))
    off = np.cumsum([0] + [len(v) for v, _, _ in parts])[:-1]
    return (
        np.concatenate([v for v, _, _ in parts]),
        np.concatenate([f + o for (_, f, _), o in zip(parts, off, strict=True)]),
        np.concatenate([c for _, _, c in parts]),
    )


def make_negative_views(count: int, out: Path, num_landmarks: int, seed: int = 0, views: Any = None) -> Path:
    """Renders of ``count`` scenes without a person (:func:`random_objects`), labels all NaN (heatmaps
    of zero: the detector learns to find nothing there). Same file layout as :func:`make_training_views`."""
    from blsm.io import atomic_write
    from blsm.learn.markerless.multiview import ViewConfig, render_scan

    if out.exists():
        return out
    vcfg = ViewConfig() if views is None else views
    rng = np.random.default_rng(seed + 7919)
    imgs, boxes, owner = [], [], []
    for i in range(count):
        v, f, c = random_objects(rng)
        cams, bx, im = render_scan(v, f, c, vcfg)
        boxes.append(bx)
        imgs.append(np.stack(im))
        owner += [i] * len(cams)
    n = sum(len(b) for b in boxes)
    with atomic_write(out, "wb") as fh:
        np.savez(
            fh,
            images=np.concatenate(imgs),
            boxes=np.concatenate(boxes),
            uv=np.full((n, num_landmarks, 2), np.nan, np.float32),
            scan=np.array(owner),
            ids=np.array([]),
        )
    return out


class _Views(torch.utils.data.Dataset):
    """Augmented crops of the rendered views (see the module docstring)."""

    def __init__(
        self, data: dict, index: np.ndarray, cfg: DetectorTrainConfig, mirror: list[int], train: bool
    ) -> None:
        self.d, self.index, self.cfg, self.mirror, self.train = data, index, cfg, mirror, train

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        i = int(self.index[k])
        cfg = self.cfg
        rng = np.random.default_rng(None if self.train else i)
        img, box, uv = self.d["images"][i], self.d["boxes"][i], self.d["uv"][i].astype(np.float64)
        if self.train:
            growth = rng.uniform(*cfg.growth_range)
            crop = crop_box(box, growth, tuple(rng.uniform(-cfg.shift, cfg.shift, 2)))
        else:
            crop = crop_box(box, CROP_GROWTH)
        x = crop_square(img, crop, cfg.size).astype(np.float32) / 255.0
        p = (uv - crop[:2]) * cfg.size / (crop[2] - crop[0])  # crop pixels
        if self.train:
            if rng.random() < 0.5:
                x = x[:, ::-1]
                p = p[self.mirror]
                p[:, 0] = cfg.size - p[:, 0]
            gain = 1.0 + rng.uniform(-cfg.color, cfg.color) + rng.uniform(-cfg.color / 2, cfg.color / 2, 3)
            mean = x.mean()
            x = np.clip((x - mean) * (1.0 + rng.uniform(-cfg.color, cfg.color)) + mean, 0, 1) * gain
            x = np.clip(x, 0.0, 1.0)
        x = np.ascontiguousarray(x.transpose(2, 0, 1), dtype=np.float32)
        return torch.from_numpy(x), torch.from_numpy(p.astype(np.float32))


def _pixel_error(net: LandmarkNet, loader: Any, size: int) -> float:
    """Median over views and landmarks of the decoded detection's distance to the label, crop pixels."""
    errs = []
    net.eval()
    with torch.no_grad():
        for x, p in loader:
            h = net(x)
            uv, _ = decode_heatmaps(h)
            e = (uv * size / h.shape[-1] - p).norm(dim=-1).flatten()
            errs.append(e[torch.isfinite(e)])
    net.train()
    return float(torch.cat(errs).median())


def detector_loss(h: torch.Tensor, uv: torch.Tensor, cfg: DetectorTrainConfig) -> torch.Tensor:
    """Weighted heatmap MSE (x 1000) plus ``coord_weight`` times the soft-argmax L1 error (cells).

    Args:
        h: (B, L, H, W) predicted heatmaps; uv: (B, L, 2) labels in cells (NaN: none).
    """
    b, n, hh, ww = h.shape
    target = gaussian_heatmaps(uv, hh, cfg.sigma)
    loss = ((h - target).square() * (1.0 + cfg.fg_weight * target)).mean() * 1000.0
    ok = torch.isfinite(uv).all(-1)
    if cfg.coord_weight > 0 and ok.any():
        prob = torch.softmax(cfg.beta * h.reshape(b, n, -1), -1).reshape(b, n, hh, ww)
        c = torch.arange(hh, dtype=h.dtype) + 0.5
        soft = torch.stack([(prob.sum(-2) * c).sum(-1), (prob.sum(-1) * c).sum(-1)], -1)
        loss = loss + cfg.coord_weight * (soft - torch.nan_to_num(uv)).abs().sum(-1)[ok].mean()
    return loss


def train_detector(
    views_files: list[Path],
    out: Path,
    cfg: DetectorTrainConfig = DetectorTrainConfig(),
    log: Callable[[str], None] = print,
) -> dict:
    """Train :class:`LandmarkNet` on the files of :func:`make_training_views` (and
    :func:`make_negative_views`); write it with :func:`save_detector`.

    Returns:
        The report (also in the file's meta): config, scans, views, per-epoch loss and validation error.
    """
    from blsm.learn.scans.format import landmark_names

    names = list(landmark_names())
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("images", "boxes", "uv", "scan")}
    for f in views_files:
        with np.load(f) as z:
            if z["uv"].shape[1] != len(names):
                raise ValueError(f"{f}: labels for {z['uv'].shape[1]} landmarks, the table has {len(names)}")
            offset = max((int(s.max()) + 1 for s in parts["scan"]), default=0)
            for k in parts:
                parts[k].append(z[k] + offset if k == "scan" else z[k])
    data = {k: np.concatenate(v) for k, v in parts.items()}
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    scans = np.unique(data["scan"])
    val_scans = rng.choice(scans, max(1, int(round(cfg.val_fraction * len(scans)))), replace=False)
    is_val = np.isin(data["scan"], val_scans)
    mirror = mirror_index(names)
    train_set = _Views(data, np.flatnonzero(~is_val), cfg, mirror, True)
    val_set = _Views(data, np.flatnonzero(is_val), cfg, mirror, False)
    loader = torch.utils.data.DataLoader(train_set, batch_size=cfg.batch, shuffle=True, drop_last=True)
    val_loader = torch.utils.data.DataLoader(val_set, batch_size=32)
    net = LandmarkNet(len(names), cfg.widths)
    if cfg.init is not None:
        from blsm.pose2d.landmark_net import load_detector

        net.load_state_dict(load_detector(cfg.init)[0].state_dict())
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    steps = cfg.epochs * len(loader)
    sched = torch.optim.lr_scheduler.OneCycleLR(
        opt, cfg.lr, total_steps=max(steps, 1), pct_start=0.05, final_div_factor=100.0
    )
    hm = cfg.size // 4
    report: dict[str, Any] = {
        "config": asdict(cfg),
        "scans": int(len(scans)),
        "val_scans": val_scans.tolist(),
        "train_views": len(train_set),
        "val_views": len(val_set),
        "epochs": [],
    }
    t0 = time.time()
    for epoch in range(cfg.epochs):
        total = 0.0
        for x, p in loader:
            loss = detector_loss(net(x), p * hm / cfg.size, cfg)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += float(loss.detach())
        err = _pixel_error(net, val_loader, cfg.size)
        report["epochs"].append(
            {"loss": total / max(len(loader), 1), "val_median_px": err, "seconds": time.time() - t0}
        )
        log(
            f"[detector] epoch {epoch + 1}/{cfg.epochs}: loss {total / max(len(loader), 1):.4f}, "
            f"validation median error {err:.2f} px of {cfg.size} ({time.time() - t0:.0f} s)"
        )
        meta = {
            "names": names,
            "size": cfg.size,
            "growth": CROP_GROWTH,
            "widths": list(cfg.widths),
            "trained_on": [str(f) for f in views_files],
            "report": report,
        }
        save_detector(net, out, meta)  # after every epoch: a stopped run leaves a usable detector
    return report


def add_parser(sub: Any, help_text: str, wrap: Callable) -> None:
    """``blsm train-landmark-detector POPULATION [...] --out FILE``."""
    p = sub.add_parser(
        "train-landmark-detector",
        help=help_text,
        description="Render textured stand-in scan populations and train the 2D landmark "
        "detector used by `blsm register --markerless`.",
    )
    p.add_argument(
        "populations", nargs="+", type=Path, help="population folders (blsm scans make) with gt_points"
    )
    p.add_argument("--out", type=Path, required=True, help="the detector file (.pt)")
    p.add_argument(
        "--views-cache", type=Path, default=None, help="the rendered views (.npz; default <out>.views.npz)"
    )
    p.add_argument("--epochs", type=int, default=DetectorTrainConfig.epochs)
    p.add_argument("--size", type=int, default=DetectorTrainConfig.size)
    p.add_argument(
        "--negatives", type=int, default=40, help="scenes without a person rendered as negatives (40)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=wrap("train-landmark-detector", _cmd))


def _cmd(args: argparse.Namespace) -> int:
    if args.epochs < 1 or args.size < 32 or args.size % 32 or args.negatives < 0:
        raise ValueError(
            f"--epochs must be >= 1, --size a multiple of 32 and --negatives >= 0, "
            f"got {args.epochs}, {args.size}, {args.negatives}"
        )
    for pop in args.populations:
        if not (pop / "scans").is_dir():
            raise ValueError(f"{pop}: not a population folder (no scans/)")
    torch.set_num_threads(max(1, torch.get_num_threads()))
    cache = args.views_cache or args.out.with_suffix(".views.npz")
    log = lambda m: print(m, file=sys.stderr, flush=True)  # noqa: E731
    make_training_views(args.populations, cache, args.seed, log)
    files = [cache]
    if args.negatives > 0:
        from blsm.learn.scans.format import landmark_names

        files.append(
            make_negative_views(
                args.negatives, cache.with_suffix(".negatives.npz"), len(landmark_names()), args.seed
            )
        )
    report = train_detector(
        files, args.out, DetectorTrainConfig(epochs=args.epochs, size=args.size, seed=args.seed), log
    )
    print(
        json.dumps(
            {
                "out": str(args.out),
                **{k: report[k] for k in ("scans", "train_views", "val_views")},
                "val_median_px": report["epochs"][-1]["val_median_px"],
            }
        )
    )
    return 0
