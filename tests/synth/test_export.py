"""Export to SPIN-style .npz and COCO keypoint JSON: fields, mapping, RLE, atomic refusal to overwrite."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from fakes import make_dataset

from synth import format as fmt
from synth.cli import main
from synth.data import DatasetIndex
from synth.export import COCO_FILE, COCO_KEYPOINTS, SPIN_FILE, SPIN_KEYPOINTS, export, rle_encode

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
        "imgname": (n,), "center": (n, 2), "scale": (n,), "part": (n, 24, 3), "S": (n, 24, 4),
        "pose": (n, 47), "angles": (n, 47), "bone": (n, 10), "shape": (n, 64), "global_orient": (n, 3),
        "transl_cam": (n, 3), "K": (n, 3, 3), "has_smpl": (n,), "has_blsm": (n,),
    }  # fmt: skip
    assert {k: data[k].shape for k in data.files} == shapes
    assert (data["has_smpl"] == 0).all() and (data["has_blsm"] == 1).all()
    spin = [s for s, _ in SPIN_KEYPOINTS]
    for r, (key, _, q, meta) in enumerate(expected):
        assert data["imgname"][r] == f"images/{key}.png" and (tmp_path / "out" / data["imgname"][r]).is_file()
        names = meta["keypoint_names"]
        x0, y0, x1, y1 = q["box"]
        np.testing.assert_allclose(data["center"][r], [(x0 + x1) / 2, (y0 + y1) / 2])
        np.testing.assert_allclose(data["scale"][r], 1.2 * max(x1 - x0, y1 - y0) / 200)
        k = names.index("left_wrist")
        np.testing.assert_allclose(data["part"][r, spin.index("l_wrist"), :2], q["keypoints_2d"][k])
        assert data["part"][r, spin.index("l_wrist"), 2] == float(q["visible"][k] and q["in_frame"][k])
        np.testing.assert_allclose(data["S"][r, spin.index("pelvis_mpii")], [*q["keypoints_3d_cam"][0], 1.0])
        np.testing.assert_allclose(data["transl_cam"][r], q["keypoints_3d_cam"][0])
        assert (data["part"][r, spin.index("thorax_mpii")] == 0).all() and data["S"][
            r, spin.index("jaw_h36m"), 3
        ] == 0
        np.testing.assert_allclose(data["pose"][r], q["blsm"]["pose"])
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
    for ann, (key, p, q, meta) in zip(doc["annotations"], expected, strict=True):
        assert ann["image_id"] == meta["index"] and ann["iscrowd"] == 0 and ann["category_id"] == 1
        kp = np.asarray(ann["keypoints"], float).reshape(17, 3)
        names = meta["keypoint_names"]
        for j, n in enumerate(COCO_KEYPOINTS):
            k = names.index(n)
            v = 2 if q["visible"][k] and q["in_frame"][k] else 1 if q["in_frame"][k] else 0
            assert kp[j, 2] == v
            np.testing.assert_allclose(kp[j, :2], q["keypoints_2d"][k] if v else [0, 0])
        assert ann["num_keypoints"] == int((kp[:, 2] > 0).sum())
        x0, y0, x1, y1 = q["box"]
        assert ann["bbox"] == [x0, y0, x1 - x0, y1 - y0] and ann["area"] == q["pixels"]
        mask = fmt.decode_png(index.read(keys.index(key), ["mask.png"])["mask.png"])
        np.testing.assert_array_equal(rle_decode(ann["segmentation"]), mask == p + 1)


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

    from synth.shards import ShardWriter

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
