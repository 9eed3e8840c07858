"""A 2D detector of the scan landmarks, learnt on renders of textured stand-in scans.

The landmark registration (thesis Sec. 5.4.1, Eqs. 5.13-5.25) needs the 74 anthropometric landmarks
of ``blsm/data/landmarks.yaml`` located on the scan; CAESAR had them placed by hand. Without them the
thesis (Sec. 6.3) detects 2D keypoints in renders of the scan and triangulates (Eq. 6.3); its
detectors (OpenPose, DensePose) were trained on labelled photographs, which we do not have. What we
do have is the truth of every stand-in scan: each landmark's surface point. :class:`LandmarkNet` is a
heatmap network (as SimpleBaselines / HRNet: one Gaussian heatmap per landmark, mean-squared error)
trained on the multi-view renders of training scans (:mod:`blsm.learn.markerless.landmark_detector`), and
:class:`LandmarkDetector` runs it on the views of a new scan; the detections are triangulated as
MediaPipe's are (:func:`blsm.learn.markerless.keypoints.triangulate_all`) and fill the scan's landmarks.

Network (small, from scratch; the renders are a narrow domain): a residual U-Net. Encoder at strides
2-32 (channels 24, 32, 64, 128, 192), decoder back to stride 4 with skip connections, one 1x1 head
of L heatmaps at ``input / 4``. Every landmark is labelled in every view, seen or not (like BlazePose's
landmarks): the position of a hidden one is inferred from the body, and the robust triangulation
drops the views that disagree.

Decoding (:func:`decode_heatmaps`): DARK's sub-cell refinement of the arg-max (a Newton step on the
smoothed log heatmap), mapped back to image pixels through the crop; the confidence is the peak
value (targets peak at 1).

Crops (:func:`crop_square`): the square of ``growth`` (1.25) times the person box's longer side
around the box centre, resized to ``size`` pixels (PIL, antialiased); outside the image is the
render background.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from blsm.camera import Camera

DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1] / "data" / "landmark_detector.pt"
"""Where a packaged detector would be (``scripts/landmark_detector.py --package``). None is
packaged: the one trained on CPU here is less accurate than MediaPipe (docs/markerless.md)."""

CROP_GROWTH = 1.25


def mirror_index(names: list[str] | tuple[str, ...]) -> list[int]:
    """For each landmark, the index of its left/right counterpart (``_l`` <-> ``_r``; itself on the midline)."""
    swap = {"_l": "_r", "_r": "_l"}
    out = []
    for n in names:
        m = n[:-2] + swap[n[-2:]] if n[-2:] in swap else n
        out.append(names.index(m) if m in names else names.index(n))
    return out


def crop_box(
    box: np.ndarray, growth: float = CROP_GROWTH, shift: tuple[float, float] = (0.0, 0.0)
) -> np.ndarray:
    """(4,) the square crop ``(x0, y0, x1, y1)`` of ``growth`` times the box's longer side around its
    centre (moved by ``shift`` times the side), pixels."""
    x0, y0, x1, y1 = (float(v) for v in box)
    side = growth * max(x1 - x0, y1 - y0, 1.0)
    cx, cy = 0.5 * (x0 + x1) + shift[0] * side, 0.5 * (y0 + y1) + shift[1] * side
    return np.array([cx - side / 2, cy - side / 2, cx + side / 2, cy + side / 2])


def crop_square(
    image: np.ndarray, crop: np.ndarray, size: int, fill: tuple[int, int, int] | None = None
) -> np.ndarray:
    """(size, size, 3) uint8: the image inside ``crop`` (pixels, may exceed the image), resized.

    Outside the image is ``fill`` (default: the image's corner colour, the render background).
    """
    from PIL import Image

    h, w = image.shape[:2]
    x0, y0, x1, y1 = crop
    pad = int(np.ceil(max(0.0, -x0, -y0, x1 - w, y1 - h))) + 1
    if fill is None:
        fill = tuple(int(c) for c in image[0, 0])
    padded = np.empty((h + 2 * pad, w + 2 * pad, 3), np.uint8)
    padded[:] = np.asarray(fill, np.uint8)
    padded[pad : pad + h, pad : pad + w] = image
    box = (x0 + pad, y0 + pad, x1 + pad, y1 + pad)
    return np.array(
        Image.fromarray(padded).resize((size, size), Image.Resampling.BILINEAR, box=box, reducing_gap=None)
    )


class _Block(nn.Module):
    """Two 3x3 convolutions (the first with ``stride``), BatchNorm, ReLU, and a residual."""

    def __init__(self, cin: int, cout: int, stride: int = 1) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
            nn.Conv2d(cout, cout, 3, 1, 1, bias=False), nn.BatchNorm2d(cout),
        )  # fmt: skip
        self.skip = (
            nn.Identity() if cin == cout and stride == 1
            else nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))
        )  # fmt: skip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(self.body(x) + self.skip(x))


class LandmarkNet(nn.Module):
    """Residual U-Net: (B, 3, S, S) images in [0, 1] -> (B, L, S/4, S/4) heatmaps.

    Args:
        num_landmarks: L.
        widths: encoder channels at strides 2, 4, 8, 16, 32.
    """

    def __init__(self, num_landmarks: int, widths: tuple[int, ...] = (24, 32, 64, 128, 192)) -> None:
        super().__init__()
        w = widths
        self.stem = nn.Sequential(
            nn.Conv2d(3, w[0], 3, 2, 1, bias=False), nn.BatchNorm2d(w[0]), nn.ReLU(inplace=True)
        )
        self.down = nn.ModuleList([_Block(w[i], w[i + 1], 2) for i in range(len(w) - 1)])
        self.up = nn.ModuleList([_Block(w[i + 1] + w[i], w[i]) for i in range(len(w) - 2, 0, -1)])
        self.head = nn.Conv2d(w[1], num_landmarks, 1)
        self.register_buffer("mean", torch.tensor([0.5, 0.5, 0.5]).view(1, 3, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        feats = [self.stem(x - self.mean)]
        for blk in self.down:
            feats.append(blk(feats[-1]))
        y = feats[-1]
        for blk, skip in zip(self.up, feats[-2:0:-1], strict=True):
            y = nn.functional.interpolate(y, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            y = blk(torch.cat([y, skip], 1))
        return self.head(y)


def gaussian_heatmaps(uv: torch.Tensor, size: int, sigma: float) -> torch.Tensor:
    """(B, L, size, size) Gaussian targets (peak 1) at ``uv`` (B, L, 2) in heatmap cells (centres at
    integer + 0.5); a NaN position gives an all-zero map."""
    c = torch.arange(size, dtype=uv.dtype, device=uv.device) + 0.5
    dx = (c[None, None, :] - uv[..., :1]) ** 2  # (B, L, size)
    dy = (c[None, None, :] - uv[..., 1:]) ** 2
    h = torch.exp(-(dy[..., :, None] + dx[..., None, :]) / (2 * sigma**2))
    return torch.nan_to_num(h, nan=0.0)


def decode_heatmaps(h: torch.Tensor, sigma: float = 1.5) -> tuple[torch.Tensor, torch.Tensor]:
    """Heatmaps (B, L, H, W) -> (positions (B, L, 2) in cells, centres at integer + 0.5; peaks (B, L)).

    DARK decoding (Zhang et al., CVPR 2020): the heatmap is smoothed with a Gaussian of ``sigma``
    cells, and the arg-max cell refined by one Newton step on the log heatmap (central differences:
    offset ``-H^-1 g``, limited to one cell). Exact for Gaussian heatmaps away from the border.
    The peak is the raw heatmap's maximum.
    """
    b, n, hh, ww = h.shape
    peak = h.reshape(b, n, -1).max(-1).values
    r = max(1, int(round(3 * sigma)))
    k = torch.exp(-(torch.arange(-r, r + 1, dtype=h.dtype, device=h.device) ** 2) / (2 * sigma**2))
    k = k / k.sum()
    x = h.reshape(b * n, 1, hh, ww)
    x = nn.functional.conv2d(nn.functional.pad(x, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    x = nn.functional.conv2d(nn.functional.pad(x, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
    x = x.reshape(b, n, hh, ww)
    scale = x.reshape(b, n, -1).max(-1).values.clamp_min(1e-12)
    lg = torch.log((x / scale[..., None, None]).clamp_min(1e-10))
    idx = x.reshape(b, n, -1).argmax(-1)
    iy, ix = idx // ww, idx % ww
    lp = nn.functional.pad(lg, (1, 1, 1, 1), mode="replicate")

    def at(dy: int, dx: int) -> torch.Tensor:
        return lp.reshape(b, n, -1).gather(-1, ((iy + 1 + dy) * (ww + 2) + ix + 1 + dx)[..., None])[..., 0]

    c = at(0, 0)
    gx, gy = 0.5 * (at(0, 1) - at(0, -1)), 0.5 * (at(1, 0) - at(-1, 0))
    hxx, hyy = at(0, 1) - 2 * c + at(0, -1), at(1, 0) - 2 * c + at(-1, 0)
    hxy = 0.25 * (at(1, 1) - at(1, -1) - at(-1, 1) + at(-1, -1))
    det = hxx * hyy - hxy**2
    ok = (det > 1e-8) & (hxx < 0)
    safe = torch.where(ok, det, torch.ones_like(det))
    dx = torch.where(ok, -(hyy * gx - hxy * gy) / safe, torch.zeros_like(det)).clamp(-1, 1)
    dy = torch.where(ok, -(hxx * gy - hxy * gx) / safe, torch.zeros_like(det)).clamp(-1, 1)
    return torch.stack([ix.to(h.dtype) + dx + 0.5, iy.to(h.dtype) + dy + 0.5], -1), peak


@dataclass
class LandmarkDetector:
    """The trained :class:`LandmarkNet` as a detector: ``detector(images, boxes, cameras) -> [(L, 3)] * C``
    rows ``(x, y, confidence)`` in image pixels, in the order of :attr:`names`.

    Attributes:
        weights: a file written by :func:`save_detector` (default: the packaged one).
        flip: also run the mirrored crop and average the heatmaps (test-time flip, as HRNet does).
        name: recorded with the results.
    """

    weights: Path | str | None = None
    flip: bool = True
    name: str = "blsm landmark detector"

    def __post_init__(self) -> None:
        path = Path(self.weights) if self.weights is not None else DEFAULT_WEIGHTS
        if self.weights is None and not path.is_file():
            raise ValueError(f"{path}: no packaged landmark detector (train one with `blsm train-landmark-detector` "
                             "and pass its file)")
        self.net, self.meta = load_detector(path)
        self.names: list[str] = list(self.meta["names"])
        self.mirror = mirror_index(self.names)
        self.name = f"{self.name} ({path.name})"

    @torch.no_grad()
    def __call__(self, images, boxes: np.ndarray, cameras: list[Camera] = ()) -> list[np.ndarray]:  # noqa: ANN001
        size, growth = int(self.meta["size"]), float(self.meta["growth"])
        crops = [crop_box(b, growth) for b in boxes]
        x = torch.stack(
            [
                torch.from_numpy(crop_square(img, c, size)).permute(2, 0, 1)
                for img, c in zip(images, crops, strict=True)
            ]
        )
        out = []
        for i in range(0, len(x), 8):
            xb = x[i : i + 8].float() / 255.0
            h = self.net(xb)
            if self.flip:  # the mirrored crop, its heatmaps mirrored back and sides exchanged
                hf = self.net(xb.flip(-1)).flip(-1)[:, self.mirror]
                h = 0.5 * (h + hf)
            uv, peak = decode_heatmaps(h)
            scale = size / h.shape[-1]
            for j in range(len(uv)):
                c = crops[i + j]
                px = uv[j].numpy() * scale * (c[2] - c[0]) / size + c[:2]
                out.append(np.concatenate([px, peak[j].numpy()[:, None].clip(0, 1)], 1))
        return out


def save_detector(net: LandmarkNet, path: str | Path, meta: dict) -> None:
    """Write the weights (float16) and ``meta`` (``names``, ``size``, ``growth``, ``widths``, ...)."""
    from blsm.io import atomic_write

    state = {k: (v.half() if v.is_floating_point() else v) for k, v in net.state_dict().items()}
    with atomic_write(path, "wb") as fh:
        torch.save({"format": "blsm-landmark-detector", "version": 1, "meta": meta, "state": state}, fh)


def load_detector(path: str | Path) -> tuple[LandmarkNet, dict]:
    """(network in eval mode, meta) from :func:`save_detector`'s file; a wrong file is a ValueError naming it."""
    path = Path(path)
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 (any unreadable file is the same user error)
        raise ValueError(f"{path}: not a landmark detector file ({type(exc).__name__})") from None
    if not isinstance(blob, dict) or blob.get("format") != "blsm-landmark-detector":
        raise ValueError(
            f"{path}: not a landmark detector file (format {blob.get('format') if isinstance(blob, dict) else '?'})"
        )
    meta = blob["meta"]
    net = LandmarkNet(len(meta["names"]), tuple(meta["widths"]))
    net.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in blob["state"].items()})
    return net.eval(), meta
