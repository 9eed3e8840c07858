"""``recovery predict default PATH`` without ``--box`` (recovery.predict.predict_people): every person of
a folder of photographs and of a short video, an image without people, and bad input (one line, exit
status 2, nothing written)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from recovery.cli import main

PERSON_KEYS = {"box", "score", "detector_keypoints", "pose", "angles", "bone", "shape", "global_orient",
               "cam", "transl", "keypoints_3d_cam", "keypoints_2d", "crop", "K_crop", "mesh"}


def _astronaut_small() -> np.ndarray:
    skimage_data = pytest.importorskip("skimage.data")
    return np.ascontiguousarray(skimage_data.astronaut()[::4, ::4])  # 128 x 128


def _save(path: Path, image: np.ndarray) -> Path:
    from PIL import Image

    Image.fromarray(image).save(path)
    return path


def _error(capsys, argv: list[str], *needles: str) -> str:
    capsys.readouterr()
    assert main(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("recovery: error: "), lines
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


@pytest.fixture(scope="module")
def photos(tmp_path_factory) -> Path:
    """one.png: the astronaut; two.jpg: the astronaut beside her mirror image."""
    a = _astronaut_small()
    folder = tmp_path_factory.mktemp("photos")
    _save(folder / "one.png", a)
    _save(folder / "two.jpg", np.concatenate([a, a[:, ::-1]], 1))
    (folder / "notes.txt").write_text("not an image: skipped")
    return folder


def test_predict_every_person_of_a_folder(photos, tmp_path, capsys):
    from PIL import Image

    out = tmp_path / "out"
    assert main(["predict", "default", str(photos), "--out", str(out)]) == 0
    assert "3 people in 2 images" in capsys.readouterr().out
    doc = json.loads((out / "people.json").read_text())
    assert doc["kind"] == "folder" and doc["task"] == "hmr_blsm"
    assert doc["detector"] == {"name": "movenet_multipose", "passes": "multi", "size": 256, "min_score": 0.2,
                               "overlap": 0.5, "look": "movenet_lightning"}
    names = doc["keypoint_names"]
    assert [e["image"] for e in doc["images"]] == ["one.png", "two.jpg"]
    assert [len(e["people"]) for e in doc["images"]] == [1, 2]
    for e in doc["images"]:
        w, h = e["width"], e["height"]
        k = np.array(e["K"])
        assert np.allclose(k, [[max(w, h), 0, w / 2], [0, max(w, h), h / 2], [0, 0, 1]])
        for p in e["people"]:
            assert set(p) == PERSON_KEYS
            x0, y0, x1, y1 = p["box"]
            assert 0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h and 0.25 <= p["score"] <= 1
            assert p["crop"]["center"] == [(x0 + x1) / 2, (y0 + y1) / 2]
            assert p["crop"]["side"] == pytest.approx(1.2 * max(x1 - x0, y1 - y0))
            assert len(p["pose"]) == len(p["angles"]) == 47 and len(p["global_orient"]) == 3
            assert p["transl"][2] > 0 and np.array(p["detector_keypoints"]).shape == (17, 3)
            kp3, kp2 = np.array(p["keypoints_3d_cam"]), np.array(p["keypoints_2d"])
            assert kp3.shape == (len(names), 3) and kp2.shape == (len(names), 2)
            uv = kp3 @ k.T
            assert np.allclose(kp2, uv[:, :2] / uv[:, 2:], atol=1e-3)  # projected with the image's K
            pelvis = kp2[names.index("pelvis")]
            assert x0 - 0.2 * (x1 - x0) <= pelvis[0] <= x1 + 0.2 * (x1 - x0)  # the body is where the box is
            lines = (out / p["mesh"]).read_text().splitlines()
            assert sum(ln.startswith("v ") for ln in lines) == 7002
        with Image.open(out / e["overlay"]) as im:
            assert im.size == (2 * w, h)  # boxes | meshes
            panel = np.asarray(im.convert("RGB")).astype(int)
        assert np.abs(panel[:, w:] - panel[:, :w]).sum() > 0  # the meshes changed the right half
    two = doc["images"][1]["people"]
    a, b = sorted((p["box"] for p in two), key=lambda bx: bx[0])
    assert a[2] <= b[0]  # the two people's boxes are disjoint
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["people.json", "one_overlay.png", "two_overlay.png", "one_person0.obj", "two_person0.obj",
         "two_person1.obj"])
    assert not list(tmp_path.glob(".out.predict-*"))  # the staging folder is gone
    # The folder run predicts each person from its box's crop, MoveNet's decoding steered by the person's
    # detector keypoints; --box (no detector, so no guide) predicts from the same crop unsteered. To float
    # rounding: the batch of two and the batch of one round differently, and the packaged checkpoint's
    # 30-step test-time fit (Adam) carries that rounding on, to 0.009 rad on a loosely constrained atom on
    # 2026-12-06 (the translation to 1e-7 m).
    from recovery.predict import box_crop, camera, predict_crops, read_image
    from recovery.predictor import load_predictor

    p = doc["images"][1]["people"][1]
    pr, image = load_predictor("default"), read_image(photos / "two.jpg")
    k = camera(image.shape[1], image.shape[0])
    guided, _ = predict_crops(pr, image, [box_crop(p["box"])], k, [np.array(p["detector_keypoints"])])
    plain, _ = predict_crops(pr, image, [box_crop(p["box"])], k)
    assert np.allclose(guided.transl[0].numpy(), p["transl"], atol=1e-4)
    assert np.allclose(guided.pose[0].numpy(), p["pose"], atol=0.02)
    assert main(["predict", "default", str(photos / "two.jpg"), "--out", str(tmp_path / "box"),
                 "--box", *map(str, p["box"])]) == 0
    single = json.loads((tmp_path / "box" / "params.json").read_text())
    assert np.allclose(single["transl"], plain.transl[0].numpy(), atol=1e-4)
    assert np.allclose(single["pose"], plain.pose[0].numpy(), atol=0.02)


def test_small_people_of_a_wide_photograph_and_the_single_pass(tmp_path, capsys):
    """Three people 112 px tall on a 1024 px wide image: the default detector (several passes) writes
    each; one pass on the whole image (--detect-passes single) sees them 28 px tall and finds none."""
    from PIL import Image

    skimage_data = pytest.importorskip("skimage.data")
    small = np.asarray(Image.fromarray(skimage_data.astronaut()).resize((112, 112), Image.LANCZOS))
    canvas = np.full((384, 1024, 3), 128, np.uint8)
    corners = [(100, 80), (460, 20), (840, 260)]
    for x, y in corners:
        canvas[y:y + 112, x:x + 112] = small
    img = _save(tmp_path / "three.png", canvas)
    assert main(["predict", "default", str(img), "--out", str(tmp_path / "multi")]) == 0
    people = json.loads((tmp_path / "multi" / "people.json").read_text())["images"][0]["people"]
    assert len(people) == 3
    for (x, y), p in zip(corners, sorted(people, key=lambda q: q["box"][0]), strict=True):
        x0, y0, x1, y1 = p["box"]
        assert x - 5 <= x0 < x1 <= x + 117 and y - 5 <= y0 < y1 <= y + 117, (x, y, p["box"])
        assert (tmp_path / "multi" / p["mesh"]).is_file()
    capsys.readouterr()
    assert main(["predict", "default", str(img), "--out", str(tmp_path / "single"),
                 "--detect-passes", "single"]) == 0
    assert f"{img}: no person found" in capsys.readouterr().out
    doc = json.loads((tmp_path / "single" / "people.json").read_text())
    want = {"name": "movenet_multipose", "passes": "single", "size": 256, "min_score": 0.25}
    assert doc["detector"] == want
    assert doc["images"][0]["people"] == []


def test_an_image_without_people_is_listed_empty(tmp_path, capsys):
    img = _save(tmp_path / "grey.png", np.full((96, 128, 3), 128, np.uint8))
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("the user's")
    assert main(["predict", "default", str(img), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"{img}: no person found" in printed and "0 people in 1 images" in printed
    doc = json.loads((out / "people.json").read_text())
    assert doc["kind"] == "image" and len(doc["images"]) == 1
    assert doc["images"][0]["people"] == [] and doc["images"][0]["note"] == "no person found"
    assert (out / "grey_overlay.png").is_file() and (out / "mine.txt").read_text() == "the user's"


def test_predict_a_short_video(tmp_path):
    av = pytest.importorskip("av")
    a = _astronaut_small()
    video = tmp_path / "clip.mp4"
    with av.open(str(video), "w") as c:
        s = c.add_stream("mpeg4", rate=10)
        s.width, s.height, s.pix_fmt = 128, 128, "yuv420p"
        for i in range(5):
            frame = np.roll(a, 4 * i, axis=1)
            for packet in s.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")):
                c.mux(packet)
        for packet in s.encode():
            c.mux(packet)
    out = tmp_path / "out"
    argv = ["predict", "default", str(video), "--out", str(out), "--every", "2", "--max-frames", "2"]
    assert main(argv) == 0
    doc = json.loads((out / "people.json").read_text())
    assert doc["kind"] == "video"
    assert [e["frame"] for e in doc["images"]] == [0, 2]
    assert doc["images"][0]["time"] == pytest.approx(0.0) and doc["images"][1]["time"] == pytest.approx(0.2)
    for e in doc["images"]:
        assert len(e["people"]) == 1 and (e["width"], e["height"]) == (128, 128)
        assert (out / e["overlay"]).is_file() and (out / e["people"][0]["mesh"]).is_file()
    assert doc["images"][0]["overlay"] == "frame_000000_overlay.png"
    # the box follows her: frame 2 is the picture rolled 8 px to the right
    x0, x1 = doc["images"][0]["people"][0]["box"][0], doc["images"][1]["people"][0]["box"][0]
    assert 4 <= x1 - x0 <= 12


def test_bad_input_is_one_line_and_writes_nothing(photos, tmp_path, capsys):
    from PIL import Image

    garbage = tmp_path / "garbage.png"
    garbage.write_bytes(b"not a png")
    empty = tmp_path / "empty"
    empty.mkdir()
    texts = tmp_path / "texts"
    texts.mkdir()
    (texts / "a.txt").write_text("x")
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"\0\1\2 not a video" * 50)
    mixed = tmp_path / "mixed"  # a good photograph, then one that cannot be read: found after some work
    mixed.mkdir()
    Image.open(photos / "one.png").save(mixed / "a.png")
    (mixed / "b.png").write_bytes(b"truncated")
    user = tmp_path / "user"  # a folder the user made: left as it was
    user.mkdir()
    (user / "people.json").write_text("the user's")
    cases = [
        ([str(garbage)], f"{garbage}: not a readable image"),
        ([str(empty)], f"{empty}: empty folder"),
        ([str(texts)], f"{texts}: no images"),
        ([str(broken)], f"{broken}: not a readable video"),
        ([str(tmp_path / "nowhere")], f"{tmp_path / 'nowhere'}: no such image, folder or video"),
        ([str(mixed)], f"{mixed / 'b.png'}: not a readable image"),
        ([str(photos), "--box", "1", "1", "20", "20"], f"{photos}: --box and --whole predict one person"),
        ([str(photos / "one.png"), "--box", "0", "0", "500", "20"], "--box", "is not inside"),
        ([str(photos), "--every", "0"], "--every must be >= 1"),
    ]
    before = sorted(p.name for p in tmp_path.iterdir())
    for args, *needles in cases:
        for out in (tmp_path / "out", user):
            _error(capsys, ["predict", "default", *args, "--out", str(out)], *needles)
    assert not (tmp_path / "out").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no staging folder left behind
    assert sorted(p.name for p in user.iterdir()) == ["people.json"]
    assert (user / "people.json").read_text() == "the user's"
