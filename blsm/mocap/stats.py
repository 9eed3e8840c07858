"""How often each pose atom sits at its limit across a motion library, and a bar chart of it.

An atom is "at its limit" in a frame when its angle is within ``tol`` (default 1 degree) of
``theta_min`` or ``theta_max``. Retargeting goes through Eq. 6, so a pose the source makes but the
limits forbid shows up as frames pinned at the limit. An atom pinned in more than 5 % of the frames
points at the limit (too tight for real motion), not at the data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FLAG = 0.05


@dataclass
class LimitHits:
    """Fractions of frames at the lower / upper limit, per atom."""

    names: list[str]
    lower: np.ndarray  # (D,)
    upper: np.ndarray  # (D,)
    frames: int
    tol_deg: float

    def flagged(self, threshold: float = FLAG) -> list[tuple[str, str, float]]:
        """(atom, "min"|"max", fraction) for every limit hit in more than ``threshold``."""
        out = []
        for n, lo, hi in zip(self.names, self.lower, self.upper, strict=True):
            if lo > threshold:
                out.append((n, "min", float(lo)))
            if hi > threshold:
                out.append((n, "max", float(hi)))
        return out


def limit_hits(angles: np.ndarray, limits: np.ndarray, names: list[str], tol_deg: float = 1.0) -> LimitHits:
    """Count limit hits.

    Args:
        angles: (N, D) atom angles in radians (all frames of the library).
        limits: (D, 2) ``[theta_min, theta_max]`` in radians.
        names: D atom names.
        tol_deg: how close to a limit counts as at it, degrees.
    """
    angles = np.asarray(angles, dtype=np.float64)
    limits = np.asarray(limits, dtype=np.float64)
    if angles.ndim != 2 or angles.shape[1] != limits.shape[0] or len(names) != limits.shape[0]:
        raise ValueError(f"angles must be (N, {limits.shape[0]}), got {angles.shape}")
    tol = math.radians(tol_deg)
    return LimitHits(
        names=list(names),
        lower=(angles <= limits[:, 0] + tol).mean(0),
        upper=(angles >= limits[:, 1] - tol).mean(0),
        frames=int(angles.shape[0]),
        tol_deg=tol_deg,
    )


def plot_limit_hits(hits: LimitHits, out_path: str | Path, threshold: float = FLAG, title: str = "") -> Path:
    """Horizontal bar chart (one row per atom; min hits to the left, max hits to the right) as PNG."""
    from PIL import Image, ImageDraw, ImageFont

    from blsm.render import save_png

    row, label_w, half_w, pad = 18, 170, 300, 10
    top = 52
    n = len(hits.names)
    width = label_w + 2 * half_w + 2 * pad + 60
    height = top + n * row + 40
    img = Image.new("RGB", (width, height), "white")
    d = ImageDraw.Draw(img)
    font = ImageFont.load_default()
    cx = label_w + pad + half_w  # the axis: 0 %
    vmax = max(0.25, float(max(hits.lower.max(initial=0), hits.upper.max(initial=0))))

    def x_of(frac: float, side: int) -> float:
        return cx + side * half_w * min(frac, vmax) / vmax

    d.text(
        (pad, 6),
        title or f"Frames at a joint limit (within {hits.tol_deg:g} deg), {hits.frames} frames",
        fill="black",
        font=font,
    )
    d.text((label_w + pad, 24), "<- at min", fill=(40, 90, 200), font=font)
    d.text((cx + half_w - 60, 24), "at max ->", fill=(200, 80, 30), font=font)
    for side in (-1, 1):
        xt = x_of(threshold, side)
        d.line([(xt, top - 4), (xt, top + n * row)], fill=(200, 0, 0), width=1)
    d.text((x_of(threshold, 1) + 3, top + n * row + 4), f"{threshold:.0%}", fill=(200, 0, 0), font=font)
    d.text((cx + half_w - 30, top + n * row + 4), f"{vmax:.0%}", fill="black", font=font)
    for i, name in enumerate(hits.names):
        y = top + i * row
        flagged = hits.lower[i] > threshold or hits.upper[i] > threshold
        if i % 2 == 0:
            d.rectangle([(0, y), (width, y + row - 1)], fill=(245, 245, 245))
        d.text((pad, y + 3), name, fill=(200, 0, 0) if flagged else "black", font=font)
        lo, hi = float(hits.lower[i]), float(hits.upper[i])
        if lo > 0:
            d.rectangle([(x_of(lo, -1), y + 3), (cx, y + row - 4)], fill=(40, 90, 200))
        if hi > 0:
            d.rectangle([(cx, y + 3), (x_of(hi, 1), y + row - 4)], fill=(200, 80, 30))
        for frac, side in ((lo, -1), (hi, 1)):
            if frac >= 0.005:
                txt = f"{frac:.0%}"
                tx = x_of(frac, side) + (4 if side > 0 else -4 - d.textlength(txt, font=font))
                d.text((tx, y + 3), txt, fill="black", font=font)
    d.line([(cx, top - 4), (cx, top + n * row)], fill="black", width=1)
    return save_png(np.asarray(img), out_path)
