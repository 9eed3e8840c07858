"""Export to SPIN-style .npz, COCO keypoint JSON and per-sequence .npz: fields, mapping, RLE, atomic
refusal to overwrite."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from fakes import make_dataset, write_fake_sequences

from synth.cli import main
from synth.dataset import format as fmt
from synth.dataset.format import CONTACT_REGIONS
from synth.dataset.index import DatasetIndex
from synth.export import (
    COCO_FILE,
    COCO_KEYPOINTS,
    SEQUENCES_FILE,
    SPIN_FILE,
    SPIN_KEYPOINTS,
    export,
    rle_encode,
)

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def root(tmp_path_factory, model):
    return make_dataset(tmp_path_factory.mktemp("fake") / "ds", num=4, shard_size=2, model=model)


def people(root) -> list[tuple[str, int, dict, dict]]:
    """(key, person, person labels, sample json) of every person with visible pixels."""
    index = DatasetIndex(root)
    out = []
    for i, (_, key, _) in enumerate(index.samples):
        meta = index.json(i)
        out += [(key, p, q, meta) for p, q in enumerate(meta["people"]) if q["pixels"] > 0]
    return out


def rle_decode(rle: dict) -> np.ndarray:
    h, w = rle["size"]
    flat = np.zeros(h * w, bool)
    pos, val = 0, False
    for c in rle["counts"]:
        flat[pos : pos + c] = val
        pos, val = pos + c, not val
    return flat.reshape((h, w), order="F")


def test_rle_round_trips_and_starts_with_zeros():
    m = np.zeros((5, 4), bool)
    m[0, 0] = m[2:4, 1:3] = True
    rle = rle_encode(m)
    assert rle["counts"][0] == 0 and sum(rle["counts"]) == 20 and rle["size"] == [5, 4]
    np.testing.assert_array_equal(rle_decode(rle), m)
    assert rle_encode(~np.ones((2, 2), bool))["counts"] == [4]


def test_spin_export_has_the_fields_and_mapping(root, tmp_path):
    path = export(root, "spin", tmp_path / "out")
    assert path == tmp_path / "out" / SPIN_FILE
    data = np.load(path, allow_pickle=False)
    expected = people(root)
    n = len(expected)
    shapes = {
        "imgname": (n,), "center": (n, 2), "scale": (n,), "part": (n, 24, 3), "visible": (n, 24), "S": (n, 24, 4),
        "pose": (n, 47), "angles": (n, 47), "bone": (n, 10), "shape": (n, 64), "global_orient": (n, 3),
        "transl_cam": (n, 3), "K": (n, 3, 3), "has_smpl": (n,), "has_blsm": (n,),
    }  # fmt: skip
    assert {k: data[k].shape for k in data.files} == shapes
    assert (data["has_smpl"] == 0).all() and (data["has_blsm"] == 1).all()
    spin = [s for s, _ in SPIN_KEYPOINTS]
    kinds: set[tuple[bool, bool]] = set()  # (inside the image, seen) of the keypoints checked
    for r, (key, _, q, meta) in enumerate(expected):
        assert data["imgname"][r] == f"images/{key}.png" and (tmp_path / "out" / data["imgname"][r]).is_file()
        names = meta["keypoint_names"]
        x0, y0, x1, y1 = q["box"]
        np.testing.assert_allclose(data["center"][r], [(x0 + x1) / 2, (y0 + y1) / 2])
        np.testing.assert_allclose(data["scale"][r], 1.2 * max(x1 - x0, y1 - y0) / 200)
        k = names.index("left_wrist")
        np.testing.assert_allclose(data["part"][r, spin.index("l_wrist"), :2], q["keypoints_2d"][k])
        # SPIN's confidence: 1 for every keypoint inside the image, occluded or not; ours apart.
        for j, (_, ours) in enumerate(SPIN_KEYPOINTS):
            if ours is not None:
                k = names.index(ours)
                assert data["part"][r, j, 2] == float(q["in_frame"][k]), (r, ours)
                assert data["visible"][r, j] == bool(q["visible"][k] and q["in_frame"][k]), (r, ours)
                kinds.add((bool(q["in_frame"][k]), bool(q["visible"][k] and q["in_frame"][k])))
        np.testing.assert_allclose(data["S"][r, spin.index("pelvis_mpii")], [*q["keypoints_3d_cam"][0], 1.0])
        np.testing.assert_allclose(data["transl_cam"][r], q["keypoints_3d_cam"][0])
        assert (data["part"][r, spin.index("thorax_mpii")] == 0).all() and data["S"][
            r, spin.index("jaw_h36m"), 3
        ] == 0
        np.testing.assert_allclose(data["pose"][r], q["blsm"]["pose"])
    assert (data["visible"].dtype == bool) and {(True, True), (True, False)} <= kinds, kinds  # seen and occluded
    # global_orient is in the camera frame: R @ R_global.
    from kornia.geometry.conversions import axis_angle_to_rotation_matrix as aa2m

    _, _, q, meta = expected[0]
    rg = aa2m(torch.tensor([q["blsm"]["global_orient"]], dtype=torch.float64))[0].numpy()
    rc = aa2m(torch.tensor(data["global_orient"][:1]))[0].numpy()
    np.testing.assert_allclose(rc, np.asarray(meta["camera"]["R"]) @ rg, atol=1e-9)


def test_coco_export_has_keypoints_boxes_and_masks(root, tmp_path):
    path = export(root, "coco", tmp_path / "coco")
    doc = json.loads(path.read_text())
    assert path.name == COCO_FILE
    assert (
        doc["categories"][0]["keypoints"] == list(COCO_KEYPOINTS)
        and len(doc["categories"][0]["skeleton"]) == 19
    )
    assert len(doc["images"]) == 4 and all(
        (tmp_path / "coco" / "images" / im["file_name"]).is_file() for im in doc["images"]
    )
    expected = people(root)
    assert len(doc["annotations"]) == len(expected)
    index = DatasetIndex(root)
    keys = [k for _, k, _ in index.samples]
    vs: set[int] = set()
    for ann, (key, p, q, meta) in zip(doc["annotations"], expected, strict=True):
        assert ann["image_id"] == meta["index"] and ann["iscrowd"] == 0 and ann["category_id"] == 1
        kp = np.asarray(ann["keypoints"], float).reshape(17, 3)
        names = meta["keypoint_names"]
        for j, n in enumerate(COCO_KEYPOINTS):
            k = names.index(n)
            v = 2 if q["visible"][k] and q["in_frame"][k] else 1 if q["in_frame"][k] else 0
            assert kp[j, 2] == v
            vs.add(v)
            np.testing.assert_allclose(kp[j, :2], q["keypoints_2d"][k] if v else [0, 0])
        assert ann["num_keypoints"] == int((kp[:, 2] > 0).sum())
        x0, y0, x1, y1 = q["box"]
        assert ann["bbox"] == [x0, y0, x1 - x0, y1 - y0] and ann["area"] == q["pixels"]
        mask = fmt.decode_png(index.read(keys.index(key), ["mask.png"])["mask.png"])
        np.testing.assert_array_equal(rle_decode(ann["segmentation"]), mask == p + 1)
    assert {1, 2} <= vs, vs  # the fixture has seen and occluded keypoints in the image


def test_export_refuses_to_overwrite_and_bad_input_is_one_line(root, tmp_path, capsys):
    export(root, "coco", tmp_path / "o")
    with pytest.raises(ValueError, match="already exists") as info:
        export(root, "coco", tmp_path / "o")
    assert "\n" not in str(info.value)
    assert export(root, "coco", tmp_path / "o", overwrite=True).is_file()
    assert not list((tmp_path / "o").glob(".*.tmp"))
    with pytest.raises(ValueError, match="unknown export format"):
        export(root, "yolo", tmp_path / "o")
    with pytest.raises(ValueError, match="manifest.json: no dataset manifest") as info:
        export(tmp_path / "missing", "spin", tmp_path / "p")
    assert "\n" not in str(info.value)
    assert main(["export", str(tmp_path / "missing"), "--format", "spin", "--out", str(tmp_path / "p")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("synth: error:") and "manifest.json" in err and "\n" not in err


def test_bad_labels_in_a_late_sample_leave_no_output(tmp_path, model):
    from fakes import make_sample

    from synth.dataset.shards import ShardWriter

    def sample(i, rng):
        fields = make_sample(i, rng, model, (256, 240))
        if i == 3:  # the last sample: every image before it would already have been copied
            doc = json.loads(fields["json"])
            del doc["people"][0]["keypoints_2d"]
            fields["json"] = fmt.encode_json(doc)
        return fields

    root = tmp_path / "ds"
    ShardWriter(out=root, num=4, shard_size=2, seed=0, config={"fake": True}).run(sample)
    for f in ("spin", "coco"):
        with pytest.raises(ValueError, match=r"shard-000001\.tar.*\.json: bad labels") as info:
            export(root, f, tmp_path / "o")
        assert "\n" not in str(info.value)
        assert not (tmp_path / "o").exists() or not any((tmp_path / "o").rglob("*")), f


T = 5


@pytest.fixture(scope="module")
def video(tmp_path_factory, model):
    return write_fake_sequences(tmp_path_factory.mktemp("fake") / "video", sequences=3, frames=T, per_shard=2,
                                model=model)  # fmt: skip


def test_sequences_export_has_the_fields_of_every_frame_and_person(video, tmp_path, capsys):
    out = tmp_path / "seq"
    assert main(["export", str(video), "--format", "sequences", "--out", str(out)]) == 0
    path = out / SEQUENCES_FILE
    assert capsys.readouterr().out.strip() == str(path)
    doc = json.loads(path.read_text())
    assert doc["sequences"] == ["000000.npz", "000001.npz", "000002.npz"] and doc["frames"] == T
    assert doc["fps"] == 30.0 and doc["contact_names"] == list(CONTACT_REGIONS)
    index = DatasetIndex(video)
    metas = [index.json(i) for i in range(len(index))]
    k, p = len(metas[0]["keypoint_names"]), len(metas[0]["people"])
    for s, name in enumerate(doc["sequences"]):
        data = np.load(out / name, allow_pickle=False)
        shapes = {
            "imgname": (T,), "frame": (T,), "time": (T,), "fps": (), "image_size": (2,), "cam_int": (T, 3, 3),
            "cam_ext": (T, 4, 4), "cam_to_world": (T, 4, 4), "pose": (p, T, 47), "global_orient": (p, T, 3),
            "transl": (p, T, 3), "bone": (p, 10), "shape": (p, 64), "keypoints_3d": (p, T, k, 3),
            "keypoints_3d_cam": (p, T, k, 3), "keypoints_2d": (p, T, k, 2), "visible": (p, T, k),
            "in_frame": (p, T, k), "velocity_3d": (p, T, k, 3), "contact": (p, T, 9),
            "contact_velocity": (p, T, 9), "contact_names": (9,), "in_view": (p, T), "box_full": (p, T, 4),
            "subject": (p,), "keypoint_names": (k,),
        }  # fmt: skip
        assert {n: data[n].shape for n in data.files} == shapes
        assert (
            data["visible"].dtype == bool and data["contact"].dtype == bool and data["in_view"].dtype == bool
        )
        assert list(data["contact_names"]) == list(CONTACT_REGIONS) and float(data["fps"]) == 30.0
        assert list(data["keypoint_names"]) == metas[0]["keypoint_names"]
        for f in range(T):
            meta = metas[s * T + f]
            assert (
                data["imgname"][f] == f"images/{s * T + f:09d}.png" and (out / data["imgname"][f]).is_file()
            )
            assert data["frame"][f] == f and data["time"][f] == pytest.approx(meta["time"])
            r, t = np.asarray(meta["camera"]["R"]), np.asarray(meta["camera"]["t"])
            np.testing.assert_allclose(data["cam_int"][f], meta["camera"]["K"])
            np.testing.assert_allclose(data["cam_ext"][f][:3], np.c_[r, t])
            np.testing.assert_allclose(data["cam_ext"][f] @ data["cam_to_world"][f], np.eye(4), atol=1e-9)
            for j, q in enumerate(meta["people"]):
                assert data["subject"][j] == q["subject"] and data["in_view"][j, f] == q["in_view"]
                for name in ("keypoints_3d", "keypoints_3d_cam", "keypoints_2d", "velocity_3d", "box_full"):
                    np.testing.assert_allclose(data[name][j, f], q[name])
                for name in ("pose", "global_orient", "transl"):
                    np.testing.assert_allclose(data[name][j, f], q["blsm"][name])
                np.testing.assert_allclose(data["bone"][j], q["blsm"]["bone"])
                np.testing.assert_array_equal(data["visible"][j, f], q["visible"])
                np.testing.assert_array_equal(
                    data["contact"][j, f], [q["contact"][c] for c in CONTACT_REGIONS]
                )
                np.testing.assert_array_equal(
                    data["contact_velocity"][j, f], [q["contact_velocity"][c] for c in CONTACT_REGIONS]
                )
        # the camera's projection of the world keypoints is the 2D keypoints
        x = data["keypoints_3d"]
        cam = (
            np.einsum("tij,ptkj->ptki", data["cam_ext"][:, :3, :3], x) + data["cam_ext"][None, :, None, :3, 3]
        )
        np.testing.assert_allclose(cam, data["keypoints_3d_cam"], atol=1e-9)
        uvw = np.einsum("tij,ptkj->ptki", data["cam_int"], cam)
        ahead = cam[..., 2] > 0.1
        np.testing.assert_allclose(
            (uvw[..., :2] / uvw[..., 2:])[ahead], data["keypoints_2d"][ahead], atol=1e-6
        )


def test_sequences_export_refuses_to_overwrite_and_bad_input_leaves_no_output(video, root, tmp_path, model):
    out = tmp_path / "o"
    export(video, "sequences", out)
    with pytest.raises(ValueError, match="sequences.json: an export already exists") as info:
        export(video, "sequences", out)
    assert "\n" not in str(info.value)
    (out / "000009.npz").write_bytes(b"")  # a sequence of an earlier, longer export ...
    doc = json.loads((out / SEQUENCES_FILE).read_text())
    (out / SEQUENCES_FILE).write_text(json.dumps({**doc, "sequences": [*doc["sequences"], "000009.npz"]}))
    export(video, "sequences", out, overwrite=True)
    assert not (out / "000009.npz").exists()  # ... goes with it
    assert sorted(p.name for p in out.glob("*.npz")) == doc["sequences"]
    assert not list(out.glob(".*.tmp"))
    # single images are not a video dataset
    with pytest.raises(ValueError, match=r"\.json: no 'sequence' label: not a video dataset") as info:
        export(root, "sequences", tmp_path / "single")
    assert "\n" not in str(info.value) and not (tmp_path / "single").exists()


def test_sequences_export_of_bad_labels_in_the_last_frame_leaves_no_output(tmp_path, model):
    from synth.dataset.shards import read_shard, write_shard

    root = write_fake_sequences(tmp_path / "v", sequences=2, frames=3, model=model)
    shard = root / "shard-000001.tar"
    samples = read_shard(shard)
    doc = json.loads(samples["000000005"]["json"])
    del doc["people"][1]["contact"]["toe_r"]
    samples["000000005"]["json"] = fmt.encode_json(doc)
    write_shard(shard, sorted((int(k), v) for k, v in samples.items()))
    man = json.loads((root / "manifest.json").read_text())
    from blsm.io import sha256_file

    man["shards"]["shard-000001.tar"]["sha256"] = sha256_file(shard)
    (root / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(
        ValueError, match=r"shard-000001\.tar:000000005\.json: bad labels \('toe_r'\)"
    ) as info:
        export(root, "sequences", tmp_path / "o")
    assert "\n" not in str(info.value)
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").rglob("*"))
