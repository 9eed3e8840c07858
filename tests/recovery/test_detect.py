"""The multi-pass person detector (recovery.detect): tiles that cover the image, the merge of the passes'
people (one person seen by two tiles is one person; a person cut by a tile's edge gives way to the
whole one), the keypoint similarity, and small people on a large canvas that one pass misses."""

from __future__ import annotations

import numpy as np
import pytest

from recovery.detect import (
    COCO_SIGMAS,
    MAX_TILES,
    MULTI_MIN_SCORE,
    Detection,
    MultiPassDetector,
    PersonDetector,
    build_detector,
    detection_tiles,
    is_cut,
    keypoint_similarity,
    merge_people,
    merged_people,
    tile_grid,
    tile_starts,
)
from recovery.models.movenet_multipose import build_multipose


def _person(x0: float, y0: float, height: float, score: float, rng: np.random.Generator,
            noise: float = 0.0, keep: slice = slice(None)) -> Detection:
    """A standing person: 17 keypoints on a stick figure of ``height`` px at ``(x0, y0)``, its box the
    keypoints' extent (only the keypoints of ``keep`` score, as a person cut by a tile's edge)."""
    u = np.array([[.5, .08], [.54, .06], [.46, .06], [.58, .08], [.42, .08], [.7, .2], [.3, .2], [.78, .38],
                  [.22, .38], [.8, .52], [.2, .52], [.62, .55], [.38, .55], [.62, .77], [.38, .77],
                  [.62, .97], [.38, .97]])
    xy = np.array([x0, y0]) + u * [height * 0.45, height] + rng.normal(0, noise, (17, 2))
    s = np.zeros(17)
    s[keep] = 0.8
    seen = xy[s > 0]
    box = np.array([seen[:, 0].min() - 5, seen[:, 1].min() - 10, seen[:, 0].max() + 5, seen[:, 1].max() + 5])
    return Detection(box=box, score=score, keypoints=np.c_[xy, s])


def test_tiles_cover_the_image_and_hold_every_small_person_whole() -> None:
    rng = np.random.default_rng(0)
    for h, w, side, overlap in ((613, 1024, 256, 0.5), (480, 640, 256, 0.34), (240, 320, 256, 0.5),
                                (1000, 300, 512, 0.5), (256, 257, 256, 0.2)):
        rects = tile_grid(h, w, side, overlap)
        covered = np.zeros((h, w), bool)
        for x0, y0, x1, y1 in rects:
            assert 0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h
            assert x1 - x0 == min(side, w) and y1 - y0 == min(side, h)  # square, cut only by the image
            covered[y0:y1, x0:x1] = True
        assert covered.all(), (h, w, side)
        for n in (h, w):  # neighbours overlap by at least overlap * side
            starts = tile_starts(n, side, overlap)
            assert starts[0] == 0 and starts[-1] == max(0, n - side)
            steps = np.diff(starts)
            assert ((steps > 0) & (steps <= side * (1 - overlap) + 1)).all()
        # any box up to overlap * side lies whole in one tile
        s = int(overlap * side)
        for _ in range(200):
            bw, bh = rng.integers(1, min(s, w) + 1), rng.integers(1, min(s, h) + 1)
            bx, by = rng.integers(0, w - bw + 1), rng.integers(0, h - bh + 1)
            assert any(x0 <= bx and y0 <= by and bx + bw <= x1 and by + bh <= y1
                       for x0, y0, x1, y1 in rects)
    # the levels: the whole image, tiles of 256 px at full scale, 512 px at half scale; none as large as
    # the image's longer side
    tiles = detection_tiles(613, 1024)
    assert tiles[0].rect == (0, 0, 1024, 613) and tiles[0].level == 0
    sides = {t.level: t.rect[2] - t.rect[0] for t in tiles[1:]}
    assert sides == {1: 256, 2: 512}
    assert len(tiles) == 1 + 7 * 4 + 3 * 2
    assert [t.level for t in detection_tiles(200, 250)] == [0]  # a small image: one pass
    # a 12 Mpixel photograph: at most MAX_TILES tiles in the finest level, coarser than full scale
    big = detection_tiles(3024, 4032)
    finest = [t for t in big if t.level == 1]
    side = finest[0].rect[2] - finest[0].rect[0]
    assert len(finest) <= MAX_TILES < len(tile_grid(3024, 4032, round(side * 0.8)))  # no coarser than need be
    assert len(big) < 2 * MAX_TILES
    with pytest.raises(ValueError, match="overlap"):
        tile_grid(100, 100, 64, 1.0)


def test_only_an_inner_tile_edge_cuts() -> None:
    rect = (256, 0, 512, 256)  # a tile at the image's top edge, inner edges left, right and below
    assert is_cut(np.array([256.0, 40, 300, 200]), rect, 613, 1024)  # at the left edge
    assert is_cut(np.array([300.0, 40, 360, 255]), rect, 613, 1024)  # at the bottom edge
    assert not is_cut(np.array([300.0, 0, 360, 200]), rect, 613, 1024)  # at the image's top edge
    assert not is_cut(np.array([300.0, 40, 360, 200]), rect, 613, 1024)
    assert not is_cut(np.array([0.0, 0, 1024, 613]), (0, 0, 1024, 613), 613, 1024)  # the whole image


def test_keypoint_similarity() -> None:
    rng = np.random.default_rng(1)
    a = _person(100, 100, 200, 0.5, rng)
    area = 90.0 * 200
    assert keypoint_similarity(a.keypoints, a.keypoints, area) == pytest.approx(1.0)
    near = _person(100, 100, 200, 0.5, rng, noise=2.0)
    assert keypoint_similarity(a.keypoints, near.keypoints, area) > 0.8
    beside = _person(160, 100, 200, 0.5, rng)  # another person, 60 px to the right: boxes overlap
    assert keypoint_similarity(a.keypoints, beside.keypoints, area) < 0.1
    # a naive loop over the shared keypoints
    shifted = a.keypoints.copy()
    shifted[:, :2] += rng.normal(0, 5, (17, 2))
    shifted[:4, 2] = 0.1  # not shared
    d2 = ((a.keypoints[4:, :2] - shifted[4:, :2]) ** 2).sum(1)
    want = np.mean([np.exp(-d2[k - 4] / (2 * area * (2 * COCO_SIGMAS[k]) ** 2)) for k in range(4, 17)])
    assert keypoint_similarity(a.keypoints, shifted, area) == pytest.approx(want)
    few = a.keypoints.copy()
    few[2:, 2] = 0.0
    assert keypoint_similarity(few, a.keypoints, area) == 0.0  # fewer than 3 shared keypoints


def test_merge_one_person_from_two_tiles_and_two_people_beside_each_other() -> None:
    rng = np.random.default_rng(2)
    one_a = _person(100, 100, 200, 0.40, rng, noise=1.5)  # one person seen by two overlapping tiles
    one_b = _person(100, 100, 200, 0.45, rng, noise=1.5)
    one_b.box = one_b.box + [4, -3, 6, 2]
    other = _person(130, 110, 190, 0.35, rng)  # a second person, partly behind the first
    assert 0.3 < _iou(one_a.box, other.box) < 0.5
    groups = merge_people([one_a, one_b, other], [False, False, False])
    assert groups == [[1, 0], [2]]  # the better view of the first person, then the second
    # by the keypoints alone: boxes of one person that overlap little (IoU < 0.5) but agree on the joints
    one_c = _person(100, 100, 200, 0.30, rng, noise=1.5)
    one_c.box = one_a.box + [-40, -30, 40, 30]
    assert _iou(one_a.box, one_c.box) < 0.5
    assert merge_people([one_a, one_c], [False, False]) == [[0, 1]]
    assert len(merge_people([one_a, one_c], [False, False], oks=1.1)) == 2  # not without the keypoints


def test_a_person_cut_by_a_tile_edge_gives_way_to_the_whole_one() -> None:
    rng = np.random.default_rng(3)
    whole = _person(300, 100, 200, 0.30, rng, noise=1.0)
    cut = _person(300, 100, 200, 0.55, rng, noise=1.0, keep=slice(0, 11))  # legs outside the tile
    cut.box[3] = 256.0  # ends at the tile's bottom edge
    flags = [is_cut(cut.box, (256, 0, 512, 256), 613, 1024), is_cut(whole.box, (0, 0, 512, 512), 613, 1024)]
    assert flags == [True, False]
    groups = merge_people([cut, whole], flags)
    assert groups == [[1, 0]]  # the whole view is kept though the cut one scores higher
    # a cut part inside a kept box, with too few keypoints to compare, joins it
    part = Detection(box=np.array([300.0, 200, 380, 256]), score=0.6, keypoints=np.zeros((17, 3)))
    assert merge_people([part, whole], [True, False]) == [[1, 0]]
    assert len(merge_people([part, whole], [False, False])) == 2  # a whole person inside is a person
    # the person: the whole view's box and keypoints with the group's best score
    (found,) = merged_people([cut, whole], flags)
    assert np.array_equal(found.box, whole.box) and np.array_equal(found.keypoints, whole.keypoints)
    assert found.score == 0.55


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    u = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - iw * ih
    return iw * ih / u


@pytest.fixture(scope="module")
def net():
    return build_multipose()


def _astronaut(side: int) -> np.ndarray:
    skimage_data = pytest.importorskip("skimage.data")
    from PIL import Image

    return np.asarray(Image.fromarray(skimage_data.astronaut()).resize((side, side), Image.LANCZOS))


# her face in the 512 px photograph, drawn by hand (tests/recovery/test_movenet.py)
FACE_BOX = np.array([180, 60, 290, 160])


def test_a_small_person_that_one_pass_misses_is_found(net) -> None:
    canvas = np.full((384, 1024, 3), 128, np.uint8)
    x, y = 300, 240
    canvas[y:y + 112, x:x + 112] = _astronaut(112)  # 112 px: 28 px at one pass's 256 px input
    assert PersonDetector(net=net)(canvas) == []
    found = MultiPassDetector(net=net)(canvas)
    assert len(found) == 1
    face = FACE_BOX * 112 / 512 + [x, y, x, y]
    b = found[0].box
    assert b[0] <= face[0] and b[1] <= face[1] and b[2] >= face[2] and b[3] >= face[3], b
    assert MULTI_MIN_SCORE <= found[0].score <= 1


def test_eight_small_people_past_the_six_of_one_pass(net) -> None:
    canvas = np.full((480, 640, 3), 128, np.uint8)
    small = _astronaut(128)
    corners = [(20 + 150 * (i % 4), 40 + 220 * (i // 4)) for i in range(8)]
    for x, y in corners:
        canvas[y:y + 128, x:x + 128] = small
    assert len(PersonDetector(net=net)(canvas)) < 8  # at most 6 a pass
    found = MultiPassDetector(net=net)(canvas)
    assert len(found) == 8  # every one of them, once: the tiles cut some, the merge keeps them whole
    for x, y in corners:
        face = FACE_BOX / 4 + [x, y, x, y]
        inside = [d for d in found if d.box[0] <= face[0] and d.box[1] <= face[1] and d.box[2] >= face[2]
                  and d.box[3] >= face[3] and d.box[2] - d.box[0] <= 140 and d.box[3] - d.box[1] <= 140]
        assert len(inside) == 1, (x, y, [d.box for d in found])
    tiles = build_detector("tiles")
    assert isinstance(tiles, MultiPassDetector) and not tiles.look
    assert isinstance(build_detector("single"), PersonDetector)
    with pytest.raises(ValueError, match="unknown detector passes"):
        build_detector("many")
