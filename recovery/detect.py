"""Find the people in a photograph with MoveNet MultiPose (:mod:`recovery.models.movenet_multipose`): one
pass on the whole image (:class:`PersonDetector`) or several, on the whole image and on overlapping
tiles, merged and checked by a second look (:class:`MultiPassDetector`, ``recovery predict``'s default).

Input size policy of a pass (MoveNet's own for MultiPose, as TF.js ``pose-detection`` runs it): the
image (or tile) is scaled so that its longer side is ``size`` pixels (default 256, MoveNet's
recommendation; 128 to 512, a multiple of 32) keeping its aspect ratio, the shorter side rounded to whole
pixels, then padded with black on the bottom or right to the next multiple of 32. The scaling is
bilinear with antialiasing (``torch.nn.functional.interpolate(antialias=True)``, half-pixel centres):
TF.js resizes without a prefilter, which aliases a large photograph; both map pixel centres alike, so
coordinates go back by the per-axis scale alone. Larger ``size`` finds smaller people at about the
square of the cost.

One pass: a person is kept when its score (the centre peak times the mean of its confident keypoint
scores, :func:`recovery.models.movenet_multipose.decode_multipose`) is at least ``min_score``: 0.25 by
default, the ``minPoseScore`` default of TF.js ``pose-detection`` for MoveNet. Its box is clipped to
the image; people are returned by descending score. A pass sees at most 6 people, and MoveNet finds a
person from about 100 px tall at its input: at 256 px a 1024 px wide photograph shows a 150 px tall
person 37 px tall, and one pass misses it.

Several passes (:class:`MultiPassDetector`), after SAHI's sliced inference (Akyon et al., ICIP 2022):

1. passes (:func:`detection_tiles`): the whole image as above, then levels of square tiles, each tile
   scaled to ``size``: tiles of ``size`` image pixels at full scale (a person 100 to 200 px tall is 100
   to 200 px at the input), then of ``2 size`` at half scale (people of 200 to 400 px), ``4 size`` ...
   while the tile is smaller than the image's longer side. Neighbouring tiles of a level overlap by half
   a tile (:data:`TILE_OVERLAP`), so any person up to half a tile lies whole in one tile of the level,
   and a larger one whole in a tile of the next level or in the whole image. The finest level has at
   most :data:`MAX_TILES` tiles: on a large photograph it starts coarser than full scale. Each pass
   gives up to 6 people; those scoring at least :data:`CANDIDATE_SCORE` (0.1) are candidates.
2. merge (:func:`merge_people`): candidates whose box ends at a tile edge inside the image
   (:func:`is_cut`, within 3 % of the tile's side) are cut; greedy non-maximum suppression takes the
   whole candidates first, then the cut ones, each by descending score, and a candidate joins a person
   already kept when their boxes' IoU is at least 0.5 (:data:`MERGE_IOU`), their keypoints' similarity
   (COCO's OKS over the keypoints both see, :func:`keypoint_similarity`) at least 0.5
   (:data:`MERGE_OKS`), or, for a cut candidate, 60 % of its box lies in the kept box
   (:data:`CUT_INSIDE`). A person keeps its first candidate's box and keypoints and the best score of
   its group.
3. second look (:func:`second_look`, on by default): MoveNet SinglePose Lightning on the square crop of
   1.25 times the box's longer side about its centre; the person's score becomes the mean of its
   MultiPose score and the look's mean keypoint score, and it is kept from :data:`MULTI_MIN_SCORE`
   (0.2). On the dev set it lifts three half-hidden people that MultiPose scores under 0.2 over the
   threshold, drops one, and lets in a tree that MultiPose scores 0.12 (SinglePose 0.36); most
   candidates that are no person (a foot, a microphone stand, a camera) stay under it.

The defaults (the two levels' scales, the half-tile overlap, 0.1 and 0.2, the mean of the two scores)
were chosen on the transfer dev set (``experiments/predict/detect_devset.py``, docs/recovery.md), the same 14
photographs the numbers there come from. Boxes come from MultiPose alone: widening a cut person's box to
the second look's keypoints helped three people of the dev set and lost one, so it is not done.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from recovery.models.backbones.movenet import MoveNet
from recovery.models.movenet_multipose import MoveNetMultiPose, MultiPoseOutput, build_multipose

MIN_SCORE = 0.25
"""Default person score threshold (TF.js pose-detection's ``minPoseScore`` for MoveNet)."""
SIZE = 256
"""Default longer side of the detector's input, pixels (MoveNet MultiPose's recommendation)."""
MULTI_MIN_SCORE = 0.2
"""Default person score threshold of the multi-pass detector (chosen on the transfer dev set)."""
CANDIDATE_SCORE = 0.1
"""Multi-pass: the people of every pass scoring at least this are candidates for the merge."""
MAX_TILES = 64
"""At most this many tiles in the finest level (a 1024 x 683 photograph has 35 at full scale; a
4032 x 3024 one would have 713, so its finest tiles are coarser)."""
TILE_OVERLAP = 0.5
"""Neighbouring tiles of a level overlap by at least this fraction of their side."""
CUT_MARGIN = 0.03
"""A box within this fraction of its tile's side of an inner tile edge is cut by it."""
MERGE_IOU = 0.5
"""Two candidates are one person when their boxes' IoU is at least this, ..."""
MERGE_OKS = 0.5
"""... or their keypoints' similarity (:func:`keypoint_similarity`) is at least this, ..."""
CUT_INSIDE = 0.6
"""... or a cut candidate lies at least this fraction of its box's area inside a kept person's box."""
LOOK_CONTEXT = 1.25
"""The second look's square crop: this times the box's longer side, about the box's centre."""
OKS_MIN_SCORE = 0.3
"""Keypoints count in :func:`keypoint_similarity` from this score."""
COCO_SIGMAS = np.array([0.026, 0.025, 0.025, 0.035, 0.035, 0.079, 0.079, 0.072, 0.072, 0.062, 0.062, 0.107,
                        0.107, 0.087, 0.087, 0.089, 0.089])
"""COCO's per-keypoint OKS constants (order of :data:`recovery.models.backbones.movenet.COCO_KEYPOINTS`)."""


@dataclass
class Detection:
    """One person found in an image (image pixels, pixel centres at integer + 0.5).

    Attributes:
        box: (4,) ``x0, y0, x1, y1``.
        score: the person score in [0, 1].
        keypoints: (17, 3) COCO keypoints ``(x, y, score)``
            (:data:`recovery.models.backbones.movenet.COCO_KEYPOINTS`).
    """

    box: np.ndarray
    score: float
    keypoints: np.ndarray


def letterbox(image: np.ndarray, size: int = SIZE) -> tuple[torch.Tensor, tuple[float, float]]:
    """(H, W, 3) uint8 RGB -> the detector's input (1, 3, H', W') in 0..255 (longer side ``size``,
    padded with black to multiples of 32) and the per-axis scales ``(sx, sy)`` from image to input."""
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3), got {image.shape}")
    h, w = image.shape[:2]
    s = size / max(h, w)
    nh, nw = max(1, round(h * s)), max(1, round(w * s))
    x = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float()
    x = F.interpolate(x, size=(nh, nw), mode="bilinear", align_corners=False, antialias=nh < h or nw < w)
    ph, pw = -(-nh // 32) * 32, -(-nw // 32) * 32
    x = F.pad(x.clamp(0, 255), (0, pw - nw, 0, ph - nh))
    return x, (nw / w, nh / h)


class PersonDetector:
    """MoveNet MultiPose behind :meth:`__call__`: an image in, its people out (module docstring).

    Args:
        size: longer side of the detector's input in pixels (a multiple of 32, 128 to 512).
        min_score: the person score threshold in [0, 1].
        net: the network (default: :func:`build_multipose` with its committed weights).
    """

    def __init__(self, size: int = SIZE, min_score: float = MIN_SCORE,
                 net: MoveNetMultiPose | None = None) -> None:
        if size % 32 or not 128 <= size <= 512:
            raise ValueError(f"the detector's size must be a multiple of 32 in [128, 512], got {size}")
        if not 0.0 <= min_score <= 1.0:
            raise ValueError(f"the person score threshold must be in [0, 1], got {min_score}")
        self.size, self.min_score = size, min_score
        self.net = net if net is not None else build_multipose()

    @torch.no_grad()
    def __call__(self, image: np.ndarray) -> list[Detection]:
        """(H, W, 3) uint8 RGB -> the people scoring at least ``min_score``, best first."""
        h, w = image.shape[:2]
        x, scale = letterbox(image, self.size)
        found = people_of_pass(self.net(self.net.normalize(x)), 0, scale, (0, 0, w, h), self.min_score)
        return sorted(found, key=lambda d: -d.score)


def people_of_pass(out: MultiPoseOutput, i: int, scale: tuple[float, float], rect: tuple[int, int, int, int],
                   min_score: float) -> list[Detection]:
    """The people of input ``i`` of a MultiPose batch scoring at least ``min_score`` (and above 0), in
    image pixels: the input shows the image region ``rect`` ``(x0, y0, x1, y1)`` scaled by ``scale``
    ``(sx, sy)``; boxes are clipped to ``rect``. In the network's order (by centre peak)."""
    x0, y0, x1, y1 = rect
    sx, sy = scale
    boxes = out.boxes[i].double() / torch.tensor([sx, sy, sx, sy], dtype=torch.float64)
    boxes += torch.tensor([x0, y0, x0, y0], dtype=torch.float64)
    boxes[:, 0::2] = boxes[:, 0::2].clamp(x0, x1)
    boxes[:, 1::2] = boxes[:, 1::2].clamp(y0, y1)
    kps = out.keypoints[i].double()
    kps[..., 0] = kps[..., 0] / sx + x0
    kps[..., 1] = kps[..., 1] / sy + y0
    found = []
    for j in range(out.scores.shape[1]):
        score, b = float(out.scores[i, j]), boxes[j]
        if score < min_score or score <= 0 or b[2] <= b[0] or b[3] <= b[1]:  # fill; in the padding
            continue
        found.append(Detection(box=b.numpy(), score=score, keypoints=kps[j].numpy()))
    return found


# -- several passes: the whole image and overlapping tiles -----------------------------------------
@dataclass(frozen=True)
class Tile:
    """A region the multi-pass detector runs MoveNet MultiPose on.

    Attributes:
        rect: ``(x0, y0, x1, y1)`` whole image pixels.
        level: 0 for the whole image, 1 for the finest tiles, 2 for tiles twice their side, ...
    """

    rect: tuple[int, int, int, int]
    level: int


def tile_starts(n: int, side: int, overlap: float) -> list[int]:
    """Start offsets of tiles of ``side`` pixels along an axis of ``n`` pixels: the first at 0, the last
    at ``n - side``, evenly spread with neighbours overlapping by at least ``overlap * side``."""
    if n <= side:
        return [0]
    count = math.ceil((n - side) / (side * (1.0 - overlap))) + 1
    return [round(i * (n - side) / (count - 1)) for i in range(count)]


def tile_grid(height: int, width: int, side: int,
              overlap: float = TILE_OVERLAP) -> list[tuple[int, int, int, int]]:
    """Square tiles ``(x0, y0, x1, y1)`` of ``side`` pixels covering a ``height x width`` image, row by row
    (cut to the image where it is smaller than ``side``)."""
    if side < 1 or not 0.0 <= overlap < 1.0:
        raise ValueError(f"tiles need a positive side and an overlap in [0, 1), got {side}, {overlap}")
    return [(x, y, min(width, x + side), min(height, y + side))
            for y in tile_starts(height, side, overlap) for x in tile_starts(width, side, overlap)]


def detection_tiles(height: int, width: int, size: int = SIZE, overlap: float = TILE_OVERLAP,
                    finest: float = 1.0, max_tiles: int = MAX_TILES) -> list[Tile]:
    """The multi-pass detector's regions: the whole image, then levels of square tiles of side
    ``size / s`` image pixels for ``s = f, f / 2, f / 4, ...`` (each tile is scaled by ``s`` to ``size``
    pixels) as long as that side is smaller than the image's longer side. ``f`` is ``finest``, or less
    (by steps of 0.8) where the finest level would have more than ``max_tiles`` tiles: a large
    photograph is searched for people of ``100 / f`` px and more, not 100 px."""
    tiles = [Tile((0, 0, width, height), 0)]
    s = finest
    while len(tile_grid(height, width, round(size / s), overlap)) > max_tiles:
        s *= 0.8
    level = 1
    while round(size / s) < max(height, width):
        tiles += [Tile(r, level) for r in tile_grid(height, width, round(size / s), overlap)]
        s, level = s / 2, level + 1
    return tiles


def is_cut(box: np.ndarray, rect: tuple[int, int, int, int], height: int, width: int,
           margin: float = CUT_MARGIN) -> bool:
    """Whether ``box`` ends within ``margin`` times the tile's longer side of an edge of the tile ``rect``
    that lies inside the image (an image edge cuts nobody the other passes would see whole)."""
    x0, y0, x1, y1 = rect
    m = margin * max(x1 - x0, y1 - y0)
    return bool((x0 > 0 and box[0] - x0 < m) or (y0 > 0 and box[1] - y0 < m)
                or (x1 < width and x1 - box[2] < m) or (y1 < height and y1 - box[3] < m))


def box_iou(a: np.ndarray, b: np.ndarray) -> float:
    """IoU of two ``x0, y0, x1, y1`` boxes."""
    inter = _intersection(a, b)
    union = _area(a) + _area(b) - inter
    return inter / union if union > 0 else 0.0


def keypoint_similarity(a: np.ndarray, b: np.ndarray, area: float, min_score: float = OKS_MIN_SCORE) -> float:
    """COCO's object keypoint similarity of two (17, 3) keypoint sets ``(x, y, score)`` of one size:
    the mean over keypoints both score at least ``min_score`` on of ``exp(-d^2 / (2 area k^2))``, ``k``
    twice :data:`COCO_SIGMAS`, ``area`` in square pixels; 0 when fewer than 3 keypoints are shared."""
    both = (a[:, 2] >= min_score) & (b[:, 2] >= min_score)
    if both.sum() < 3 or area <= 0:
        return 0.0
    d2 = ((a[both, :2] - b[both, :2]) ** 2).sum(1)
    return float(np.exp(-d2 / (2.0 * area * (2.0 * COCO_SIGMAS[both]) ** 2)).mean())


def merge_people(people: list[Detection], cut: list[bool], iou: float = MERGE_IOU, oks: float = MERGE_OKS,
                 inside: float = CUT_INSIDE) -> list[list[int]]:
    """Greedy non-maximum suppression over the candidates of every pass: whole people before cut ones
    (:func:`is_cut`), each by descending score; a candidate joins a person already kept when their
    boxes' IoU is at least ``iou``, their keypoints' similarity (:func:`keypoint_similarity`, with the
    larger box's area) at least ``oks``, or, for a cut candidate, at least ``inside`` of its box's area
    lies in the kept box. Returns the people as lists of candidate indices, the kept one first."""
    order = sorted(range(len(people)), key=lambda i: (cut[i], -people[i].score))
    groups: list[list[int]] = []
    for i in order:
        a = people[i]
        for g in groups:
            b = people[g[0]]
            if (box_iou(a.box, b.box) >= iou
                    or keypoint_similarity(a.keypoints, b.keypoints, max(_area(a.box), _area(b.box))) >= oks
                    or (cut[i] and _intersection(a.box, b.box) >= inside * _area(a.box))):
                g.append(i)
                break
        else:
            groups.append([i])
    return groups


def merged_people(people: list[Detection], cut: list[bool]) -> list[Detection]:
    """The people of :func:`merge_people`: each its kept candidate's box and keypoints with the best
    score of its group (a cut view may score higher than the whole one)."""
    return [Detection(box=people[g[0]].box, score=max(people[i].score for i in g),
                      keypoints=people[g[0]].keypoints) for g in merge_people(people, cut)]


def _area(b: np.ndarray) -> float:
    return float(max(0.0, b[2] - b[0]) * max(0.0, b[3] - b[1]))


def _intersection(a: np.ndarray, b: np.ndarray) -> float:
    return float(max(0.0, min(a[2], b[2]) - max(a[0], b[0])) * max(0.0, min(a[3], b[3]) - max(a[1], b[1])))


@torch.no_grad()
def second_look(net: MoveNet, image: np.ndarray, boxes: list[np.ndarray], context: float = LOOK_CONTEXT,
                batch: int = 16) -> np.ndarray:
    """MoveNet SinglePose ``net`` on the square crop of side ``context`` times each box's longer side
    about its centre (antialiased, zeros outside the image): (N, 17, 3) keypoints ``(x, y, score)`` in
    image pixels."""
    from synth.dataset.crops import crop_affine, map_points, warp_to_crop

    if not boxes:
        return np.zeros((0, 17, 3))
    src = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1).float() / 255.0
    n = net.input_size
    affines = []
    for b in boxes:
        side = context * max(b[2] - b[0], b[3] - b[1], 1.0)
        affines.append(crop_affine(((b[0] + b[2]) / 2, (b[1] + b[3]) / 2), side, n))
    out = []
    for k in range(0, len(boxes), batch):
        crops = torch.stack([warp_to_crop(src, a, n) for a in affines[k:k + batch]])
        out.append(net.keypoints(net.run(net.normalize(crops))).double().numpy())
    kps = np.concatenate(out)
    for kp, a in zip(kps, affines, strict=True):
        kp[:, :2] = map_points(kp[:, :2], np.linalg.inv(a))
    return kps


class MultiPassDetector:
    """MoveNet MultiPose on the whole image and on overlapping tiles, merged, each person scored again by
    a second look (module docstring): an image in, its people out.

    Args:
        size: every pass's input, longer side, pixels (a multiple of 32, 128 to 512).
        min_score: the person score threshold in [0, 1].
        look: score each person with MoveNet SinglePose Lightning too (:func:`second_look`): its score
            is then the mean of the MultiPose score and the look's mean keypoint score.
        overlap: neighbouring tiles' overlap, a fraction of their side in [0, 0.9].
        candidate_score: the people of each pass scoring at least this (or ``min_score`` if lower) are
            merged.
        net: the MultiPose network (default: :func:`build_multipose`); it is put in channels-last
            memory format (the same values, about 1.3 times faster on a CPU).
        look_net: the SinglePose network (default: ``build_movenet("movenet_lightning")``, loaded on
            the first look).
    """

    def __init__(self, size: int = SIZE, min_score: float = MULTI_MIN_SCORE, look: bool = True,
                 overlap: float = TILE_OVERLAP, candidate_score: float = CANDIDATE_SCORE,
                 net: MoveNetMultiPose | None = None, look_net: MoveNet | None = None) -> None:
        if size % 32 or not 128 <= size <= 512:
            raise ValueError(f"the detector's size must be a multiple of 32 in [128, 512], got {size}")
        if not 0.0 <= min_score <= 1.0:
            raise ValueError(f"the person score threshold must be in [0, 1], got {min_score}")
        if not 0.0 <= overlap <= 0.9:
            raise ValueError(f"the tiles' overlap must be in [0, 0.9], got {overlap}")
        self.size, self.min_score, self.look, self.overlap = size, min_score, look, overlap
        self.candidate_score = min(candidate_score, min_score)
        net = net if net is not None else build_multipose()
        self.net = net.to(memory_format=torch.channels_last)
        self._look_net = look_net

    @property
    def look_net(self) -> MoveNet:
        """The second look's network, built on first use."""
        if self._look_net is None:
            from recovery.models.backbones.movenet import build_movenet

            self._look_net = build_movenet("movenet_lightning").eval()
        return self._look_net

    @torch.no_grad()
    def candidates(self, image: np.ndarray,
                   batch: int = 8) -> tuple[list[Detection], list[bool], list[Tile]]:
        """Every pass's people (:func:`detection_tiles`) scoring at least ``candidate_score``: the people
        (MultiPose scores), whether each is cut by its tile (:func:`is_cut`) and its tile. Tiles of one
        input shape run in batches of ``batch``."""
        if image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"image must be (H, W, 3), got {image.shape}")
        h, w = image.shape[:2]
        tiles = detection_tiles(h, w, self.size, self.overlap)
        inputs = [letterbox(image[t.rect[1]:t.rect[3], t.rect[0]:t.rect[2]], self.size) for t in tiles]
        by_shape: dict[tuple[int, ...], list[int]] = {}
        for k, (x, _) in enumerate(inputs):
            by_shape.setdefault(tuple(x.shape), []).append(k)
        people, cut, source = [], [], []
        for ks in by_shape.values():
            for b in range(0, len(ks), batch):
                chunk = ks[b:b + batch]
                x = torch.cat([inputs[k][0] for k in chunk]).contiguous(memory_format=torch.channels_last)
                out = self.net(self.net.normalize(x))
                for i, k in enumerate(chunk):
                    t = tiles[k]
                    for d in people_of_pass(out, i, inputs[k][1], t.rect, self.candidate_score):
                        people.append(d)
                        cut.append(is_cut(d.box, t.rect, h, w))
                        source.append(t)
        return people, cut, source

    @torch.no_grad()
    def __call__(self, image: np.ndarray) -> list[Detection]:
        """(H, W, 3) uint8 RGB -> the people scoring at least ``min_score``, best first."""
        found = merged_people(*self.candidates(image)[:2])
        if self.look and found:
            for d, kp in zip(found, second_look(self.look_net, image, [d.box for d in found]), strict=True):
                d.score = 0.5 * (d.score + float(kp[:, 2].mean()))
        return sorted((d for d in found if d.score >= self.min_score), key=lambda d: -d.score)


DETECT_PASSES = ("multi", "tiles", "single")
"""``multi``: :class:`MultiPassDetector` with its second look; ``tiles``: the same without it;
``single``: :class:`PersonDetector`, one pass on the whole image."""


def build_detector(passes: str = "multi", size: int = SIZE,
                   min_score: float | None = None) -> PersonDetector | MultiPassDetector:
    """The detector of ``passes`` (:data:`DETECT_PASSES`); ``min_score`` defaults to :data:`MIN_SCORE`
    for one pass and :data:`MULTI_MIN_SCORE` for several."""
    if passes not in DETECT_PASSES:
        raise ValueError(f"unknown detector passes {passes!r}; known: {', '.join(DETECT_PASSES)}")
    if passes == "single":
        return PersonDetector(size, MIN_SCORE if min_score is None else min_score)
    min_score = MULTI_MIN_SCORE if min_score is None else min_score
    return MultiPassDetector(size, min_score, look=passes == "multi")
