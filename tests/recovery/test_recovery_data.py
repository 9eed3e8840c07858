"""recovery.datasets: the crop cache equals SynthDataset's crops, per-batch augmentation keeps 2D, 3D,
camera and pose labels consistent (rotation, scale, shift, flip), and the data order resumes."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from recovery_helpers import CONTEXT, CROP

from blsm.skeleton import mirror_name
from recovery.config import AugmentSpec
from recovery.datasets.augment import BatchAugment, CropParams
from recovery.datasets.cache import CropCache, build_cache, stack_items
from recovery.datasets.sampling import ResumableSampler, spread_indices
from recovery.utils.geometry import project
from synth.dataset.images import SynthDataset

MIRROR = torch.diag(torch.tensor([-1.0, 1.0, 1.0]))
TURN = CropParams(rotation_deg=23.0, scale=0.85, shift=(0.04, -0.03))


@pytest.fixture(scope="module")
def cache(cache_dir):
    return CropCache([cache_dir])


@pytest.fixture(scope="module")
def raw(cache):
    """Every cache item, stacked (uint8 images at CONTEXT times the crop's field of view)."""
    return stack_items([cache[(0, i)] for i in range(len(cache))])


def _augment(cache, model, spec=None, seed=0):
    return BatchAugment(
        CROP, cache.context, spec, seed, model.dof_mirror, cache.keypoint_names
    )


def test_cache_layout(cache, raw, fake_root):
    # 6 images, 9 people in view: samples 0, 2, 4 show two; 1, 3, 5 one (1's second is out of frame).
    assert len(cache) == 9
    side = round(CROP * CONTEXT)
    assert (
        cache.side == side
        and raw["images"].shape == (9, side, side, 3)
        and raw["images"].dtype == torch.uint8
    )
    assert cache.label("pose").shape == (9, 47)
    # A valid cache is reused, not rebuilt.
    meta = cache.folders[0] / "meta.json"
    before = meta.stat().st_mtime_ns
    assert (
        build_cache(fake_root, cache.folders[0], CROP, CONTEXT, workers=0, log=lambda *a: None)
        == cache.folders[0]
    )
    assert meta.stat().st_mtime_ns == before


def test_centre_of_the_cache_is_the_synth_dataset_crop(cache, raw, fake_root, model):
    """Un-augmented, BatchAugment's centre crop of the cache (1.8 x the box at 48 px) is SynthDataset's
    crop at SPIN's 1.2 x the box (32 px): the same pixel grid, so labels agree to rounding and the
    image to its uint8 quantisation."""
    got = _augment(cache, model)([cache[(0, i)] for i in range(len(cache))])
    ds = SynthDataset(fake_root, crop=CROP, box_scale=1.2)
    ref = stack_items([ds[i] for i in range(len(ds))])
    assert (got["keypoints_2d"][..., :2] - ref["keypoints_2d"][..., :2]).abs().max() < 1e-3  # px
    assert torch.equal(got["keypoints_2d"][..., 2], ref["keypoints_2d"][..., 2])
    assert (got["keypoints_3d"] - ref["keypoints_3d"]).abs().max() < 1e-5  # m
    assert (got["transl_cam"] - ref["transl_cam"]).abs().max() < 1e-5
    torch.testing.assert_close(got["K_crop"], ref["K_crop"], atol=1e-3, rtol=1e-6)
    torch.testing.assert_close(got["global_orient"], axis_angle_to_rotation_matrix(ref["global_orient"]), atol=1e-6, rtol=0)
    for k in ("pose", "angles", "bone", "shape"):
        assert torch.equal(got[k], ref[k]), k
    assert (got["image"] - ref["image"]).abs().max() <= 0.51 / 255
    assert torch.equal(got["mask"], ref["mask"]) and torch.equal(got["parts"], ref["parts"])
    assert got["mask"].any(1).any(1).all()  # every person has pixels in its crop


@pytest.mark.parametrize(
    "params", [TURN, CropParams(rotation_deg=-31.0, scale=1.2, shift=(-0.02, 0.05), flip=True)]
)
def test_augmented_labels_project_exactly(cache, raw, model, params):
    b = _augment(cache, model).apply(raw, [params] * len(cache))
    uv = project(b["keypoints_3d"] + b["transl_cam"][:, None], b["K_crop"])
    assert (uv - b["keypoints_2d"][..., :2]).abs().max() < 1e-3  # px, every keypoint, visible or not
    # ... and the BLSM body of the augmented parameters is the augmented skeleton.
    from recovery.models.hmr import body_outputs

    out = body_outputs(model, b["pose"], b["global_orient"], b["bone"], b["shape"])
    limit = 1e-5 if not params.flip else 2e-3  # the rig is symmetric to about a millimetre
    assert (out.keypoints_3d - b["keypoints_3d"]).norm(dim=-1).max() < limit


def test_seeded_random_augmentation_projects_exactly_and_is_repeatable(cache, model):
    spec = AugmentSpec(rotation_prob=1.0, flip_prob=0.5)
    aug = _augment(cache, model, spec, seed=3)
    items = [cache[(1, i)] for i in range(len(cache))]
    params = [aug.params(1, i) for i in range(len(cache))]
    assert any(p.flip for p in params) and not all(p.flip for p in params)
    assert all(p.rotation_deg != 0 and p.scale != 1 for p in params)
    b = aug(items)
    uv = project(b["keypoints_3d"] + b["transl_cam"][:, None], b["K_crop"])
    assert (uv - b["keypoints_2d"][..., :2]).abs().max() < 1e-3
    again = aug(items[::-1])
    assert torch.equal(again["image"], b["image"].flip(0))  # a function of (seed, epoch, item) only
    other = _augment(cache, model, spec, seed=4)(items)
    assert not torch.equal(other["keypoints_2d"], b["keypoints_2d"])


def test_flip_mirrors_everything(cache, raw, model):
    aug = _augment(cache, model)
    n = len(cache)
    plain = aug.apply(raw, [TURN] * n)
    flip = aug.apply(
        raw, [CropParams(rotation_deg=TURN.rotation_deg, scale=TURN.scale, shift=TURN.shift, flip=True)] * n
    )
    assert torch.equal(flip["pose"], model.mirror_pose(plain["pose"]))
    assert torch.equal(flip["angles"], model.mirror_pose(plain["angles"]))
    assert not torch.equal(flip["pose"], plain["pose"])
    names = cache.keypoint_names
    perm = [names.index(mirror_name(n)) for n in names]
    assert perm != list(range(len(names)))
    torch.testing.assert_close(
        flip["keypoints_3d"], plain["keypoints_3d"][:, perm] @ MIRROR, atol=1e-6, rtol=0
    )
    torch.testing.assert_close(flip["transl_cam"], plain["transl_cam"] @ MIRROR)
    torch.testing.assert_close(
        flip["global_orient"], MIRROR @ plain["global_orient"] @ MIRROR, atol=1e-6, rtol=0
    )
    u = CROP - plain["keypoints_2d"][:, perm, 0]
    torch.testing.assert_close(flip["keypoints_2d"][..., 0], u, atol=1e-4, rtol=0)
    torch.testing.assert_close(
        flip["keypoints_2d"][..., 1:], plain["keypoints_2d"][:, perm, 1:], atol=1e-4, rtol=0
    )
    # The image is the mirror image; the parts are mirrored and their left and right swapped.
    assert (flip["image"] - plain["image"].flip(-1)).abs().max() < 1e-4
    assert torch.equal(flip["mask"], plain["mask"].flip(-1))
    assert torch.equal(flip["parts"], aug.part_swap[plain["parts"].flip(-1)])
    assert not torch.equal(aug.part_swap, torch.arange(len(aug.part_swap)))


def test_flip_test_time_augmentation_undoes_the_augmentations_flip(cache, raw, model):
    """recovery.models.hmr.unflip_output is the inverse of BatchAugment's flip on every regressed
    parameter: the labels of a flipped crop, read as a prediction and mirrored back, are the
    unflipped crop's (so the flip average of two such predictions is the plain one)."""
    from recovery.models.hmr import HMROutput, flip_average, unflip_output
    from recovery.utils.geometry import translation_to_cam

    aug = _augment(cache, model)
    n = len(cache)
    plain = aug.apply(raw, [TURN] * n)
    flip = aug.apply(raw, [CropParams(rotation_deg=TURN.rotation_deg, scale=TURN.scale, shift=TURN.shift, flip=True)] * n)

    def as_output(b):
        cam = translation_to_cam(b["transl_cam"], b["K_crop"], CROP)
        return HMROutput(pose=b["pose"], orient=b["global_orient"], bone=b["bone"], shape=b["shape"], cam=cam,
                         thetas=torch.zeros(1, n, 1))

    want, back = as_output(plain), unflip_output(model, as_output(flip))
    assert not torch.allclose(as_output(flip).cam, want.cam, atol=1e-3)  # the flip changes tx
    for k in ("pose", "orient", "bone", "shape", "cam"):
        torch.testing.assert_close(getattr(back, k), getattr(want, k), atol=1e-4, rtol=0, msg=k)
    avg = flip_average(model, want, as_output(flip))
    for k in ("pose", "orient", "cam"):
        torch.testing.assert_close(getattr(avg, k), getattr(want, k), atol=1e-4, rtol=0, msg=k)
    # Two different predictions: the mean of the parameters, the orientation a rotation between.
    other = HMROutput(pose=want.pose + 0.2, orient=want.orient @ axis_angle_to_rotation_matrix(torch.tensor([[0.0, 0.4, 0.0]])),
                      bone=want.bone, shape=want.shape, cam=want.cam + 0.1, thetas=want.thetas)
    flipped_other = unflip_output(model, other)  # unflip is an involution: this is other's flipped twin
    avg = flip_average(model, want, flipped_other)
    torch.testing.assert_close(avg.pose, want.pose + 0.1, atol=1e-5, rtol=0)
    torch.testing.assert_close(avg.cam, want.cam + 0.05, atol=1e-5, rtol=0)
    rel = want.orient.transpose(1, 2) @ avg.orient  # a 0.2 rad turn about y
    torch.testing.assert_close(rel, axis_angle_to_rotation_matrix(torch.tensor([[0.0, 0.2, 0.0]])).expand_as(rel), atol=1e-5, rtol=0)


def test_resumable_sampler_continues_the_same_order():
    n, seed = 9, 5
    whole = list(itertools.islice(iter(ResumableSampler(n, seed)), 40))
    for epoch in range(4):
        keys = [i for e, i in whole if e == epoch]
        if len(keys) == n:
            assert sorted(keys) == list(range(n))  # each epoch is a permutation
    assert [i for e, i in whole if e == 0] != [i for e, i in whole if e == 1]
    for pos in range(40):
        rest = list(itertools.islice(iter(ResumableSampler(n, seed, pos // n, pos % n)), 40 - pos))
        assert rest == whole[pos:], pos
    assert list(itertools.islice(iter(ResumableSampler(n, seed + 1)), 40)) != whole
    assert [i for _, i in itertools.islice(iter(ResumableSampler(n, seed, shuffle=False)), n)] == list(
        range(n)
    )


def test_spread_indices():
    assert spread_indices(10, 0).tolist() == list(range(10))
    assert spread_indices(10, 20).tolist() == list(range(10))
    got = spread_indices(100, 7)
    assert len(got) == 7 and got[0] == 0 and np.all(np.diff(got) >= 14)


def test_missing_or_foreign_cache_is_a_one_line_error(tmp_path):
    with pytest.raises(ValueError, match=f"{tmp_path / 'meta.json'}: not a crop cache"):
        CropCache([tmp_path])
    with pytest.raises(ValueError, match="no dataset manifest here"):
        build_cache(tmp_path, tmp_path / "c", CROP, CONTEXT, workers=0)


def test_effects_touch_pixels_only_and_are_repeatable(cache, model):
    from recovery.config import EffectsSpec

    spec = AugmentSpec(rotation_prob=1.0)
    items = [cache[(1, i)] for i in range(len(cache))]
    plain = _augment(cache, model, spec, seed=3)(items)
    every = EffectsSpec(blur_prob=1.0, noise=0.05, jpeg_prob=1.0, lowres_prob=1.0, occlusion_prob=1.0)
    aug = BatchAugment(CROP, cache.context, spec, 3, model.dof_mirror, cache.keypoint_names, effects=every)
    b = aug(items)
    for k in plain:
        if k != "image":
            assert torch.equal(b[k], plain[k]), k  # labels, masks and parts as without effects
    assert b["image"].shape == plain["image"].shape and 0 <= b["image"].min() and b["image"].max() <= 1
    assert (b["image"] - plain["image"]).abs().mean() > 0.01
    again = aug(items[::-1])
    assert torch.equal(again["image"], b["image"].flip(0))  # a function of (seed, epoch, item) only
    for one in (EffectsSpec(blur_prob=1.0), EffectsSpec(noise=0.05), EffectsSpec(jpeg_prob=1.0, jpeg_quality=10),
                EffectsSpec(lowres_prob=1.0), EffectsSpec(occlusion_prob=1.0)):
        img = BatchAugment(CROP, cache.context, spec, 3, model.dof_mirror, cache.keypoint_names,
                           effects=one)(items)["image"]
        assert (img - plain["image"]).abs().mean() > 1e-3, one
    off = BatchAugment(CROP, cache.context, spec, 3, model.dof_mirror, cache.keypoint_names,
                       effects=EffectsSpec())(items)
    assert torch.equal(off["image"], plain["image"])  # all off: the crops of before
    with pytest.raises(ValueError, match="data.effects"):
        EffectsSpec(blur_prob=1.5)


def test_style_effects_touch_pixels_only_and_fda_takes_the_photographs_colour(cache, model, tmp_path):
    from PIL import Image

    from recovery.config import EffectsSpec
    from recovery.datasets.augment import fourier_style, random_convolution

    spec = AugmentSpec(rotation_prob=1.0)
    items = [cache[(1, i)] for i in range(len(cache))]
    plain = _augment(cache, model, spec, seed=3)(items)
    colour = np.array([128, 77, 179], np.uint8)  # a photograph of one colour: its spectrum is its DC term
    Image.fromarray(np.broadcast_to(colour, (40, 60, 3)).copy()).save(tmp_path / "flat.png")
    for one in (EffectsSpec(randconv_prob=1.0), EffectsSpec(fda_prob=1.0, fda_folder=str(tmp_path))):
        aug = BatchAugment(CROP, cache.context, spec, 3, model.dof_mirror, cache.keypoint_names, effects=one)
        b = aug(items)
        for k in plain:
            if k != "image":
                assert torch.equal(b[k], plain[k]), k
        assert 0 <= b["image"].min() and b["image"].max() <= 1
        assert (b["image"] - plain["image"]).abs().mean() > 1e-3, one
        assert torch.equal(aug(items[::-1])["image"], b["image"].flip(0))  # a function of (seed, epoch, item)
    x = plain["image"][:1] * 0.5 + 0.25  # away from the clamp
    rng = np.random.default_rng(0)
    y = fourier_style(x, np.broadcast_to(colour, (40, 60, 3)), 0.05, rng)
    # the DC amplitude is the photograph's: the crop's mean colour becomes the photograph's
    assert np.allclose(y.mean((0, 2, 3)).numpy(), colour / 255.0, atol=0.01)
    z = random_convolution(x, np.random.default_rng(1))
    assert z.shape == x.shape and not torch.equal(z, x)
    with pytest.raises(ValueError, match="fda_folder"):
        EffectsSpec(fda_prob=0.5)
    with pytest.raises(ValueError, match="holds no photographs"):
        BatchAugment(CROP, cache.context, spec, 3, model.dof_mirror, cache.keypoint_names,
                     effects=EffectsSpec(fda_prob=1.0, fda_folder=str(tmp_path / "none")))(items)


def test_truncation_close_ups_keep_the_head_and_project_exactly(cache, model):
    from recovery.config import EffectsSpec

    items = [cache[(1, i)] for i in range(len(cache))]
    spec = AugmentSpec(rotation_prob=0.0, flip_prob=0.0, scale=0.0, translation=0.0)
    plain = _augment(cache, model, spec, seed=3)(items)
    trunc = BatchAugment(CROP, cache.context, spec, 3, model.dof_mirror, cache.keypoint_names,
                         effects=EffectsSpec(truncation_prob=1.0, truncation_scale=0.5))
    b = trunc(items)
    uv = project(b["keypoints_3d"] + b["transl_cam"][:, None], b["K_crop"])
    assert (uv - b["keypoints_2d"][..., :2]).abs().max() < 1e-3  # the labels follow the close-up
    names = list(cache.keypoint_names)
    head, ankles = names.index("head_top"), [names.index("ankle_l"), names.index("ankle_r")]
    for i in range(len(items)):
        f = trunc.params(1, i).scale
        assert 0.5 <= f <= 0.9
        # the top edge is kept: a point's height from the top grows by 1 / f
        top_plain, top_trunc = plain["keypoints_2d"][i, head, 1], b["keypoints_2d"][i, head, 1]
        assert float(top_trunc) == pytest.approx(float(top_plain) / f, rel=1e-3, abs=1e-3)
    assert b["keypoints_2d"][:, ankles, 2].sum() < plain["keypoints_2d"][:, ankles, 2].sum()  # legs leave


def test_augment_spec_is_synth_augment_config_with_no_hue(tmp_path):
    """One augmentation config: recovery's is synth's with hue 0 by default, also when a YAML file
    sets some of its keys; synth's checks apply."""
    import dataclasses

    from recovery.config import AugmentConfig, load_config

    assert isinstance(AugmentSpec(), AugmentConfig)
    assert dataclasses.asdict(AugmentSpec()) == {**dataclasses.asdict(AugmentConfig()), "hue": 0.0}
    path = tmp_path / "c.yaml"
    path.write_text("data: {augment: {scale: 0.3}}\n")
    aug = load_config(path).data.augment
    assert aug == AugmentSpec(scale=0.3) and aug.hue == 0.0
    path.write_text("data: {augment: {hue: 0.9}}\n")
    with pytest.raises(ValueError, match=r"c\.yaml: data\.augment: augment ranges"):
        load_config(path)


def _kornia_batch_colour(img, params):
    """The colour step as recovery computed it before issue 33: SPIN's gains, then kornia's four
    adjustments on the whole batch (each when any item needs it)."""
    from kornia import enhance

    gains = torch.tensor([p.color for p in params], dtype=img.dtype)[:, :, None, None]
    x = (img * gains).clamp(0.0, 1.0)
    jit = torch.tensor([p.jitter for p in params], dtype=img.dtype)
    if (jit[:, 0] != 0).any():
        x = enhance.adjust_brightness(x, jit[:, 0])
    if (jit[:, 1] != 1).any():
        x = enhance.adjust_contrast(x, jit[:, 1])
    if (jit[:, 2] != 1).any():
        x = enhance.adjust_saturation(x, jit[:, 2])
    if (jit[:, 3] != 0).any():
        x = enhance.adjust_hue(x, jit[:, 3])
    return x.clamp(0.0, 1.0)


@pytest.mark.parametrize("hue", [0.0, 0.05])
def test_colour_is_synth_colour_jitter_per_item_and_the_batched_one_bit_for_bit(hue):
    from recovery.datasets.augment import colour, draw_params

    spec = AugmentSpec(hue=hue)
    img = torch.rand(6, 3, 16, 16, generator=torch.Generator().manual_seed(1))
    params = [draw_params(spec, np.random.default_rng([4, i])) for i in range(6)]
    assert torch.equal(colour(img, params), _kornia_batch_colour(img, params))
    assert torch.equal(colour(img, [CropParams()] * 6), img)  # the identity: no augmentation


def test_augmented_dataset_is_seeded_and_changes_only_the_image_by_colour(fake_root):
    """AugmentedDataset: a function of (seed, epoch, item) when seeded, fresh draws otherwise; with
    only the colour ranges open, every label equals the plain crop's; its items load with workers."""
    from torch.utils.data import DataLoader

    from recovery.config import AugmentConfig
    from recovery.datasets.augment import AugmentedDataset, color_jitter

    plain = SynthDataset(fake_root, crop=32)
    ds = AugmentedDataset(plain, AugmentConfig(), seed=5)
    torch.testing.assert_close(ds[2], ds[2])
    first = ds[2]["affine"]
    ds.set_epoch(1)
    assert not torch.equal(ds[2]["affine"], first)
    free = AugmentedDataset(plain, AugmentConfig())
    assert not torch.equal(free[2]["affine"], free[2]["affine"])
    colour_only = AugmentedDataset(plain, AugmentConfig(scale=0, rotation_deg=0, flip_prob=0, translation=0), seed=1)
    a, b = plain[0], colour_only[0]
    assert not torch.equal(a["image"], b["image"])
    for k in a:
        if k != "image":
            assert torch.equal(a[k], b[k]), k
    img = a["image"]
    assert torch.equal(color_jitter(img, (0.0, 1.0, 1.0, 0.0)), img)  # the identity is exact
    assert color_jitter(img, (0.1, 1.0, 1.0, 0.0)).mean() > img.mean() + 0.05
    assert color_jitter(img, (0.0, 0.5, 1.0, 0.0)).std() < img.std()
    grey = color_jitter(img, (0.0, 1.0, 0.0, 0.0))
    assert (grey.max(0).values - grey.min(0).values).abs().max() < 1e-5  # no saturation: grey
    assert not torch.allclose(color_jitter(img, (0.0, 1.0, 1.0, 0.5)), img, atol=1e-3)
    batches = list(DataLoader(ds, batch_size=2, num_workers=2))
    assert sum(len(x["image"]) for x in batches) == len(plain) and batches[0]["image"].shape[1:] == (3, 32, 32)
