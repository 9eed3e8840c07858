"""SequenceDataset: clips over the fake video sequences of :func:`fakes.write_fake_sequences`, with
crops that follow a person or whole frames, and a flip that mirrors the world frame consistently."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from fakes import make_dataset, write_fake_sequences
from torch.utils.data import DataLoader

from blsm.skeleton import mirror_name
from synth.dataset import format as fmt
from synth.dataset.format import CONTACT_REGIONS
from synth.dataset.images import mirror_permutation
from synth.dataset.index import DatasetIndex
from synth.dataset.sequences import SequenceDataset, smooth_boxes
from synth.dataset.shards import read_shard, write_shard

torch.set_num_threads(1)
T, FPS = 6, 30.0


@pytest.fixture(scope="module")
def root(tmp_path_factory, model):
    return write_fake_sequences(
        tmp_path_factory.mktemp("fake") / "seq", sequences=3, frames=T, fps=FPS, per_shard=2, model=model
    )


def test_fake_sequences_round_trip_through_the_index(root):
    man = json.loads((root / "manifest.json").read_text())
    assert man["num_samples"] == 3 * T and man["shard_size"] == 2 * T and man["complete"]
    assert man["config"]["sequence"] == {"enabled": True, "frames": T, "fps": FPS, "per_shard": 2}
    assert [e["samples"] for _, e in sorted(man["shards"].items())] == [2 * T, T]  # whole sequences
    index = DatasetIndex(root, verify=True)
    assert [int(k) for _, k, _ in index.samples] == list(range(3 * T))
    for i in range(len(index)):
        meta = index.json(i)
        s, f = divmod(i, T)
        assert (meta["index"], meta["sequence"], meta["frame"], meta["frames"]) == (i, s, f, T)
        assert meta["fps"] == FPS and meta["time"] == pytest.approx(f / FPS)
        cam = meta["camera"]
        r, t = np.asarray(cam["R"]), np.asarray(cam["t"])
        np.testing.assert_allclose(np.asarray(cam["to_world"])[:3], np.c_[r.T, -r.T @ t], atol=1e-12)
        assert cam["path"]["kind"] == "pan"
        assert [q["track"] for q in meta["people"]] == [0, 1]  # everyone, in order, in every frame
        for q in meta["people"]:
            assert set(q["contact"]) == set(CONTACT_REGIONS) == set(q["contact_velocity"])
            assert np.asarray(q["velocity_3d"]).shape == np.asarray(q["keypoints_3d"]).shape
            assert q["in_view"] == (q["pixels"] > 0)
    # the camera pans, person 0 stands in contact, the exit person of sequence 1 leaves the image
    first, last = index.json(0)["camera"]["R"], index.json(T - 1)["camera"]["R"]
    assert not np.allclose(first, last)
    assert any(index.json(f)["people"][0]["contact"]["pelvis"] is False for f in range(T))
    assert any(any(index.json(f)["people"][0]["contact"].values()) for f in range(T))
    views = [index.json(T + f)["people"][1]["in_view"] for f in range(T)]
    assert views[0] and not views[-1]
    # velocity_3d is the central difference of the posed body: close to the keypoints' own
    kp = np.array([index.json(f)["people"][1]["keypoints_3d"] for f in range(T)])
    vel = np.array([index.json(f)["people"][1]["velocity_3d"] for f in range(T)])
    np.testing.assert_allclose((kp[2:] - kp[:-2]) * FPS / 2, vel[1:-1], atol=0.05)


L, CROP = 4, 64


@pytest.fixture(scope="module")
def person(root):
    return SequenceDataset(root, clip_len=L, stride=2, mode="person", crop=CROP)


@pytest.fixture(scope="module")
def frame(root):
    return SequenceDataset(root, clip_len=L, stride=2, mode="frame", crop=CROP)


def project(item: dict, with_people: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """(R X + t, the pixels of K (R X + t)) of an item's world keypoints, float64."""
    x, r, t, k = (item[n].double() for n in ("keypoints_3d", "R", "t", "K"))
    eq = "lij,lpkj->lpki" if with_people else "lij,lkj->lki"
    pad = (slice(None), None, None) if with_people else (slice(None), None)
    cam = torch.einsum(eq, r, x) + t[pad]
    uvw = torch.einsum(eq, k, cam)
    return cam, uvw[..., :2] / uvw[..., 2:]


def test_clips_stay_in_sequences_and_need_the_person_in_view(root, person, frame):
    index = DatasetIndex(root)
    views = np.array([[q["in_view"] for q in index.json(i)["people"]] for i in range(len(index))])  # (S T, P)
    expect = []
    for s in range(3):
        for start in (0, 2):  # T = 6, L = 4, stride 2
            expect += [(s, p) for p in range(2) if views[s * T + start : s * T + start + L, p].mean() >= 0.5]
    assert [(s, p) for s, _, p in person.items] == expect
    assert len(expect) < 12  # the person leaving the image in sequence 1 loses a clip
    assert [s for s, _, _ in frame.items] == [0, 0, 1, 1, 2, 2]
    for s, samples, _ in person.items + frame.items:
        assert list(samples) == list(range(samples[0], samples[0] + L)) and samples[0] // T == s
    strict = SequenceDataset(root, clip_len=L, stride=2, crop=CROP, min_in_view=1.0)
    assert len(strict) < len(person)
    assert len(SequenceDataset(root, clip_len=T + 1, crop=CROP)) == 0


def test_dataloader_batches_the_documented_shapes(root):
    for mode in ("person", "frame"):
        ds = SequenceDataset(root, clip_len=L, stride=2, mode=mode, crop=CROP, flip_prob=0.5)
        batches = list(DataLoader(ds, batch_size=3, num_workers=2))
        assert sum(len(b["images"]) for b in batches) == len(ds)
        b, k = batches[0], len(ds.keypoint_names)
        people = () if mode == "person" else (2,)
        assert b["images"].shape == (3, L, 3, CROP, CROP) and 0 <= b["images"].min() <= b["images"].max() <= 1
        for name, shape in {
            "keypoints_2d": (L, *people, k, 3), "keypoints_3d_cam": (L, *people, k, 3),
            "keypoints_3d": (L, *people, k, 3), "velocity_3d": (L, *people, k, 3), "K": (L, 3, 3),
            "R": (L, 3, 3), "t": (L, 3), "transl": (L, *people, 3), "global_orient": (L, *people, 3),
            "pose": (L, *people, 47), "contact": (L, *people, len(CONTACT_REGIONS)),
            "contact_velocity": (L, *people, len(CONTACT_REGIONS)), "in_view": (L, *people),
            "time": (L,), "frame": (L,), "sequence": (), "track": people,
        }.items():  # fmt: skip
            assert b[name].shape == (3, *shape), name
        torch.testing.assert_close(b["time"][0], b["frame"][0].float() / FPS)


@pytest.mark.parametrize("mode", ["person", "frame"])
@pytest.mark.parametrize("flip", [False, True])
def test_the_crop_camera_projects_the_world_keypoints(person, frame, mode, flip):
    ds = person if mode == "person" else frame
    for i in range(len(ds)):
        item = ds.get(i, flip=flip)
        cam, uv = project(item, mode == "frame")
        torch.testing.assert_close(cam, item["keypoints_3d_cam"].double(), atol=1e-5, rtol=0)
        ahead = cam[..., 2] > 0.1
        kp = item["keypoints_2d"][..., :2].double()
        torch.testing.assert_close(uv[ahead], kp[ahead], atol=1e-3, rtol=0)
        assert torch.linalg.det(item["R"].double()).sub(1).abs().max() < 1e-5  # proper rotations


def test_the_person_crop_follows_the_person(person):
    for i in range(len(person)):
        item = person.get(i)
        seen = item["keypoints_2d"][..., 2] > 0
        assert seen[item["in_view"]].any(-1).all()  # the person is in the crop while in view
        kp = item["keypoints_2d"][..., :2][seen]
        assert (kp > 0).all() and (kp < CROP).all()


@pytest.mark.parametrize("mode", ["person", "frame"])
def test_flip_mirrors_image_labels_and_world_consistently(person, frame, mode):
    ds = person if mode == "person" else frame
    perm = torch.tensor(mirror_permutation(ds.keypoint_names))
    swap = [CONTACT_REGIONS.index(mirror_name(r)) for r in CONTACT_REGIONS]
    flip_cam = torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))
    for i in (0, len(ds) - 1):
        a, b = ds.get(i), ds.get(i, flip=True)
        torch.testing.assert_close(b["images"], a["images"].flip(-1), atol=1e-5, rtol=0)
        kp_a = a["keypoints_2d"][..., perm, :]
        torch.testing.assert_close(b["keypoints_2d"][..., 0], CROP - kp_a[..., 0], atol=1e-4, rtol=0)
        torch.testing.assert_close(b["keypoints_2d"][..., 1:], kp_a[..., 1:], atol=1e-4, rtol=0)
        torch.testing.assert_close(b["contact"], a["contact"][..., swap])
        torch.testing.assert_close(b["contact_velocity"], a["contact_velocity"][..., swap])
        # the mirror M: a reflection in a vertical plane (Y and the ground kept), from frame 0's camera
        r0 = a["R"][0].double()
        n = torch.tensor([r0[0, 0], 0.0, r0[0, 2]], dtype=torch.float64)
        n = n / n.norm()
        m = torch.eye(3, dtype=torch.float64) - 2 * torch.outer(n, n)
        assert abs(torch.linalg.det(m) + 1) < 1e-9
        assert torch.equal(m[1], torch.tensor([0.0, 1.0, 0.0]).double())
        x_a, x_b = a["keypoints_3d"].double()[..., perm, :], b["keypoints_3d"].double()
        torch.testing.assert_close(x_b, x_a @ m.T, atol=1e-5, rtol=0)
        torch.testing.assert_close(b["velocity_3d"].double(), a["velocity_3d"].double()[..., perm, :] @ m.T,
                                   atol=1e-5, rtol=0)  # fmt: skip
        # R' X' + t' = F (R X + t), and R' = F R M, t' = F t
        cam_a, _ = project({**a, "keypoints_3d": a["keypoints_3d"][..., perm, :]}, mode == "frame")
        cam_b, _ = project(b, mode == "frame")
        torch.testing.assert_close(cam_b, cam_a @ flip_cam, atol=1e-5, rtol=0)
        torch.testing.assert_close(b["R"].double(), flip_cam @ a["R"].double() @ m, atol=1e-6, rtol=0)
        torch.testing.assert_close(b["t"].double(), a["t"].double() @ flip_cam, atol=1e-6, rtol=0)
        # the principal point of the flipped image: cx' = W - cx (the crop's, for the crop's W)
        torch.testing.assert_close(b["K"][:, 0, 2], CROP - a["K"][:, 0, 2], atol=1e-4, rtol=0)


def test_flipped_body_parameters_pose_the_flipped_keypoints(person, model):
    """The model posed with the flipped pose, orientation and translation gives the flipped world
    keypoints (to the model's 1 mm left/right asymmetry of shape)."""
    for flip in (False, True):
        item = person.get(len(person) - 1, flip=flip)
        n = len(item["pose"])
        with torch.no_grad():
            out = model(
                pose=item["pose"], bone=item["bone"].expand(n, -1), shape=item["shape"].expand(n, -1),
                global_orient=item["global_orient"], transl=item["transl"],
            )  # fmt: skip
        err = (out.keypoints - item["keypoints_3d"]).norm(dim=-1).max()
        assert err < (1e-4 if not flip else 1.5e-3), (flip, float(err))


def test_seeded_flips_repeat_and_vary(root):
    ds = SequenceDataset(root, clip_len=L, stride=2, crop=CROP, flip_prob=0.5, seed=3)

    def flipped(d: SequenceDataset) -> list[bool]:
        # a flipped clip's K has the crop's principal point mirrored: compare with the plain clip
        return [bool((d[i]["K"][0, 0, 2] != d.get(i)["K"][0, 0, 2]).item()) for i in range(len(d))]

    first = flipped(ds)
    assert first == flipped(SequenceDataset(root, clip_len=L, stride=2, crop=CROP, flip_prob=0.5, seed=3))
    assert any(first) and not all(first)
    ds.set_epoch(1)
    assert flipped(ds) != first
    torch.testing.assert_close(ds[0]["images"], ds[0]["images"])


def test_smooth_boxes_is_a_centred_moving_average():
    rng = np.random.default_rng(0)
    centres, sides = rng.uniform(0, 100, (7, 2)), rng.uniform(10, 50, 7)
    c, s = smooth_boxes(centres, sides, 3)
    for f in range(7):
        lo, hi = max(f - 1, 0), min(f + 2, 7)
        np.testing.assert_allclose(c[f], centres[lo:hi].mean(0))
        np.testing.assert_allclose(s[f], sides[lo:hi].mean())
    assert smooth_boxes(centres, sides, 1)[0] is centres


def test_bad_input_is_one_line_naming_the_file(root, tmp_path, model):
    single = make_dataset(tmp_path / "single", num=2, shard_size=2, size=(64, 64), model=model)
    with pytest.raises(ValueError, match=r"manifest\.json: no config\.sequence"):
        SequenceDataset(single)
    with pytest.raises(ValueError, match="mode must be"):
        SequenceDataset(root, mode="clip")
    with pytest.raises(ValueError, match="min_in_view"):
        SequenceDataset(root, min_in_view=2.0)
    # a frame without velocity_3d: the clip that reads it names the sample
    bad = tmp_path / "bad"
    shutil.copytree(root, bad)
    shard = sorted(bad.glob("shard-*.tar"))[0]
    samples = read_shard(shard)
    meta = json.loads(samples["000000001"]["json"])
    del meta["people"][0]["velocity_3d"]
    samples["000000001"]["json"] = fmt.encode_json(meta)
    write_shard(shard, sorted((int(k), v) for k, v in samples.items()))
    ds = SequenceDataset(bad, clip_len=L, stride=2, crop=CROP)
    where = r"shard-000000\.tar:000000001\.json: bad labels .*velocity_3d"
    with pytest.raises(ValueError, match=where) as err:
        ds.get(0)
    assert "\n" not in str(err.value)


def test_frame_clips_pad_people_to_the_dataset_largest(root):
    ds = SequenceDataset(root, clip_len=L, mode="frame", crop=CROP)
    ds.max_people = 3  # as if another sequence had three people
    item = ds.get(0)
    assert item["track"].tolist() == [0, 1, -1] and item["valid"].tolist() == [True, True, False]
    assert item["keypoints_2d"].shape[1] == 3 and not item["keypoints_2d"][:, 2].any()
    assert item["bone"].shape[0] == 3 and not item["in_view"][:, 2].any()
