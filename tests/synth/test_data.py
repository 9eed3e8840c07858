"""SynthDataset: crops that keep keypoints, masks, parts and 3D labels consistent, with and without
rotation and flip; indexing, filtering, workers and one-line errors (the random draws of
augmentation: tests/recovery/test_recovery_data.py)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from fakes import DOT, dot_colour, make_dataset
from torch.utils.data import DataLoader

from blsm.joint_limits import angles_from_unconstrained
from blsm.skeleton import mirror_name
from synth.dataset import format as fmt
from synth.dataset.crops import crop_affine, warp_to_crop
from synth.dataset.images import SynthDataset
from synth.dataset.index import DatasetIndex

torch.set_num_threads(1)
CROP = 224
TURNS = [  # SynthDataset.get's crop geometry
    {},
    {"rotation_deg": 23.0, "scale": 0.85, "shift": (0.04, -0.03)},
    {"rotation_deg": -31.0, "scale": 1.2, "shift": (-0.02, 0.05), "flip": True},
]


@pytest.fixture(scope="module")
def root(tmp_path_factory, model):
    return make_dataset(tmp_path_factory.mktemp("fake") / "ds", model=model)


@pytest.fixture(scope="module")
def ds(root):
    return SynthDataset(root, crop=CROP)


def clean_dots(ds: SynthDataset, i: int) -> tuple[set[int], np.ndarray]:
    """Keypoints of item ``i`` whose whole DOT x DOT square survives in the source image."""
    s, _ = ds.items[i]
    src = fmt.decode_png(ds.index.read(s, ["rgb.png"])["rgb.png"])
    uv = np.floor(np.asarray(ds.index.json(s)["people"][0]["keypoints_2d"])).astype(int)
    r, out = DOT // 2, set()
    for k, (u, v) in enumerate(uv):
        blk = src[max(v - r, 0) : v + r + 1, max(u - r, 0) : u + r + 1]
        if blk.shape[:2] == (DOT, DOT) and (blk == dot_colour(k)).all():
            out.add(k)
    return out, src


def colour_at(item: dict, k: int) -> np.ndarray:
    u, v = np.floor(item["keypoints_2d"][k, :2].numpy()).astype(int)
    return item["image"][:, v, u].numpy() * 255


def test_warp_puts_pixel_centres_on_pixel_centres():
    # A 2x enlargement: every source pixel becomes exactly a 2x2 block (nearest), which holds only
    # when the half-pixel convention of kornia (centres at integers) is handled.
    src = torch.arange(20.0).reshape(1, 4, 5)
    a = crop_affine((2.5, 2.0), 4.0, 8)
    expect = src[0].repeat_interleave(2, 0).repeat_interleave(2, 1)[:, 1:9]
    torch.testing.assert_close(warp_to_crop(src, a, 8, "nearest")[0], expect)
    # A 1:1 shift: a one-pixel dot lands, bilinear and undiluted, on the pixel its centre maps to.
    img = torch.zeros(1, 30, 40)
    img[0, 11, 17] = 1.0
    a = crop_affine((20.0, 15.0), 16.0, 16)
    x, y = (a @ [17.5, 11.5, 1.0])[:2]
    assert x % 1 == 0.5 and y % 1 == 0.5
    out = warp_to_crop(img, a, 16)[0]
    expect = torch.zeros(16, 16)
    expect[int(y), int(x)] = 1.0
    torch.testing.assert_close(out, expect, atol=1e-5, rtol=0)


def test_warp_antialiases_a_shrinking_crop_and_keeps_its_geometry():
    # A one-pixel checkerboard shrunk 7.3x: bilinear sampling alone returns the pattern's 0s and
    # 1s (aliasing); the prefiltered warp returns its mean.
    yy, xx = torch.meshgrid(torch.arange(600), torch.arange(800), indexing="ij")
    board = ((xx + yy) % 2).float()[None]
    a = crop_affine((401.0, 297.0), 64 * 7.3, 64)
    inner = (slice(4, -4), slice(4, -4))
    raw = warp_to_crop(board, a, 64, antialias=False)[0][inner]
    smooth = warp_to_crop(board, a, 64)[0][inner]
    assert float(raw.std()) > 0.1 and float((raw - 0.5).abs().max()) > 0.3
    assert float((smooth - 0.5).abs().max()) < 0.02
    # A smooth image (a ramp plus a slow wave) crops to the same values with or without the
    # prefilter, at integer and fractional shrinks, rotated too: the region's offset, the blocks'
    # centres and the margin are bookkept right.
    ramp = (0.003 * xx + 0.002 * yy + 0.2 * torch.sin(xx / 60.0) * torch.cos(yy / 45.0)).float()[None]
    for side, rot in ((64 * 3.0, 0.0), (64 * 4.6, 0.0), (64 * 1.5, 0.0), (64 * 5.2, 30.0)):
        a = crop_affine((380.3, 310.7), side, 64, rotation_deg=rot)
        torch.testing.assert_close(warp_to_crop(ramp, a, 64), warp_to_crop(ramp, a, 64, antialias=False),
                                   atol=0.01, rtol=0)
    # No shrink, no change; a crop reaching past the image keeps zeros there.
    a = crop_affine((20.0, 15.0), 48.0, 64)
    torch.testing.assert_close(warp_to_crop(ramp, a, 64), warp_to_crop(ramp, a, 64, antialias=False))
    a = crop_affine((10.0, 10.0), 64 * 4.0, 64)
    out = warp_to_crop(ramp + 1.0, a, 64)[0]
    assert float(out[:20, :20].abs().max()) == 0.0 and float(out[40:, 40:].min()) > 0.9


def test_dataloader_with_two_workers_yields_documented_shapes(root):
    ds = SynthDataset(root, crop=64)
    batches = list(DataLoader(ds, batch_size=4, num_workers=2))
    assert sum(len(b["image"]) for b in batches) == len(ds)
    b, k = batches[0], len(ds.keypoint_names)
    shapes = {
        "image": (4, 3, 64, 64), "keypoints_2d": (4, k, 3), "keypoints_3d": (4, k, 3), "pose": (4, 47),
        "angles": (4, 47), "bone": (4, 10), "shape": (4, 64), "global_orient": (4, 3), "transl_cam": (4, 3),
        "K_crop": (4, 3, 3), "affine": (4, 3, 3), "mask": (4, 64, 64), "parts": (4, 64, 64),
        "index": (4,), "person": (4,),
    }  # fmt: skip
    assert {n: tuple(v.shape) for n, v in b.items()} == shapes
    assert b["parts"].dtype == torch.int64 and b["mask"].dtype == torch.bool
    assert int(b["parts"].max()) <= 6 and set(b["keypoints_2d"][..., 2].unique().tolist()) <= {0.0, 1.0}


def test_items_are_person_instances_and_filters_apply(root, ds):
    people = [ds.index.json(i)["people"] for i in range(len(ds.index))]
    assert ds.items == [(i, p) for i, pp in enumerate(people) for p, q in enumerate(pp) if q["pixels"] > 0]
    assert (1, 1) not in ds.items  # the person out of frame
    assert len(SynthDataset(root, person="largest")) == len(people)
    assert len(SynthDataset(root, min_visible=1000)) == 0
    coco = SynthDataset(root, keypoints="coco17")
    assert coco.keypoint_names[0] == "nose" and coco[0]["keypoints_2d"].shape == (17, 3)
    with pytest.raises(ValueError, match="person must be"):
        SynthDataset(root, person="first")


@pytest.mark.parametrize("params", TURNS, ids=["plain", "rotated", "flipped"])
def test_crop_puts_each_keypoint_on_its_dot(ds, params):
    for i in (0, 2):
        clean, _ = clean_dots(ds, i)
        item = ds.get(i, **params)
        source = ds._kp_perm if params.get("flip") else np.arange(len(ds.keypoint_names))
        checked = 0
        for k in range(len(source)):
            u, v = item["keypoints_2d"][k, :2]
            if source[k] in clean and 0 <= u < CROP and 0 <= v < CROP:
                np.testing.assert_allclose(colour_at(item, k), dot_colour(source[k]), atol=0.5)
                checked += 1
        assert checked >= 10


@pytest.mark.parametrize("params", TURNS, ids=["plain", "rotated", "flipped"])
def test_k_crop_and_orientation_reproduce_the_keypoints(ds, model64, params):
    for i in range(len(ds)):
        item = {k: v.double() for k, v in ds.get(i, **params).items()}
        # A pinhole with square pixels, no skew: the 3D rotation is the image's rotation.
        kc = item["K_crop"]
        torch.testing.assert_close(
            kc[[0, 1, 2, 2], [1, 0, 0, 1]], torch.zeros(4, dtype=kc.dtype), atol=1e-5, rtol=0
        )
        torch.testing.assert_close(kc[0, 0], kc[1, 1])
        proj = (item["keypoints_3d"] + item["transl_cam"]) @ item["K_crop"].T
        torch.testing.assert_close(proj[:, :2] / proj[:, 2:], item["keypoints_2d"][:, :2], atol=1e-3, rtol=0)
        # The camera-frame pose and orientation rebuild the pelvis-relative keypoints (1 mm).
        out = model64(**{n: item[n][None] for n in ("pose", "bone", "shape", "global_orient")})
        torch.testing.assert_close(
            out.keypoints[0] - out.keypoints[0, :1], item["keypoints_3d"], atol=1e-3, rtol=0
        )


def test_flip_agrees_with_the_flipped_image(ds, model64):
    base = {"rotation_deg": 17.0, "scale": 0.93, "shift": (0.01, 0.02)}
    swap = torch.tensor([0] + [1 + fmt.PART_NAMES.index(mirror_name(n)) for n in fmt.PART_NAMES])
    names = ds.keypoint_names
    for i in (0, 3):
        a, b = ds.get(i, **base), ds.get(i, **base, flip=True)
        torch.testing.assert_close(b["image"], a["image"].flip(-1), atol=1e-4, rtol=0)
        assert torch.equal(b["mask"], a["mask"].flip(-1))
        assert torch.equal(b["parts"], swap[a["parts"].flip(-1)])
        assert set(b["parts"].unique().tolist()) >= {2, 3, 4}  # left and right labels present
        clean, _ = clean_dots(ds, i)
        for k, n in enumerate(names):  # under keypoint k of the flipped crop: the dot of its mirror
            m = names.index(mirror_name(n))
            torch.testing.assert_close(b["keypoints_2d"][k, 0], CROP - a["keypoints_2d"][m, 0])
            assert b["keypoints_2d"][k, 2] == a["keypoints_2d"][m, 2]
            if m in clean and 0 <= b["keypoints_2d"][k, 0] < CROP and 0 <= b["keypoints_2d"][k, 1] < CROP:
                np.testing.assert_allclose(colour_at(b, k), dot_colour(m), atol=0.5)
        # The mirrored pose poses the mirrored body: rest orientation, x negated, left/right swapped.
        perm = [names.index(mirror_name(n)) for n in names]
        ja = model64(pose=a["pose"].double()[None]).keypoints[0]
        jb = model64(pose=b["pose"].double()[None]).keypoints[0]
        torch.testing.assert_close(
            jb, (ja * torch.tensor([-1.0, 1.0, 1.0], dtype=ja.dtype))[perm], atol=1e-3, rtol=0
        )
        # x mirrors like the angles: Eq. 6 commutes with the mirror (symmetric limit table).
        limits = model64.dof_limits
        torch.testing.assert_close(
            angles_from_unconstrained(b["pose"].double()[None], limits)[0],
            model64.mirror_pose(angles_from_unconstrained(a["pose"].double()[None], limits))[0],
        )
        torch.testing.assert_close(b["angles"], model64.mirror_pose(a["angles"].double()).float())
        lo, hi = limits[:, 0].float(), limits[:, 1].float()
        assert ((b["angles"] >= lo - 1e-6) & (b["angles"] <= hi + 1e-6)).all()


def one_line_error(call, match: str) -> str:
    with pytest.raises(ValueError, match=match) as info:
        call()
    assert "\n" not in str(info.value)
    return str(info.value)


def test_bad_datasets_give_one_line_errors(root, tmp_path):
    one_line_error(lambda: SynthDataset(tmp_path / "nothing"), "manifest.json: no dataset manifest")
    bad = tmp_path / "bad"
    shutil.copytree(root, bad)
    man = json.loads((bad / "manifest.json").read_text())
    (bad / "manifest.json").write_text(json.dumps({**man, "format": "other"}))
    one_line_error(lambda: SynthDataset(bad), "not a 'blsm-synth-shards' manifest")
    (bad / "manifest.json").write_text(json.dumps(man))
    shard = bad / "shard-000001.tar"
    data = shard.read_bytes()
    shard.write_bytes(data[: len(data) // 2])
    one_line_error(lambda: SynthDataset(bad), "shard-000001.tar")
    shard.unlink()
    one_line_error(lambda: SynthDataset(bad), "shard-000001.tar: shard listed in the manifest is missing")
    shard.write_bytes(data)
    # A corrupt member: garbage over sample 3's PNG, found when the item is read.
    index = DatasetIndex(bad)
    offset, size = index.samples[3][2]["rgb.png"]
    with open(shard, "r+b") as f:
        f.seek(offset)
        f.write(b"\x00" * size)
    ds = SynthDataset(bad)
    item = next(j for j, (s, _) in enumerate(ds.items) if s == 3)
    msg = one_line_error(lambda: ds[item], "not a readable PNG")
    assert "shard-000001.tar:000000003.rgb.png" in msg
