"""synth.preview on sequence datasets: ``synth preview --video`` (animated GIF / PNG of a sequence at
its frame rate) and ``--sheet`` (evenly spaced frames), on the fake sequences of tests/synth/fakes.py."""

from __future__ import annotations

import numpy as np
import pytest
from fakes import make_dataset, write_fake_sequences
from PIL import Image

from synth.cli import main
from synth.preview import draw_frame, read_sequence, sequence_sheet, sequence_video

FRAMES, FPS, SIZE = 6, 30.0, 64
CAPTION = 30  # rows of the corner caption (two lines of text) at scale 2, left out of comparisons


@pytest.fixture(scope="module")
def seq_root(tmp_path_factory, model):
    return write_fake_sequences(
        tmp_path_factory.mktemp("preview_video") / "ds",
        sequences=2,
        frames=FRAMES,
        fps=FPS,
        size=(SIZE, SIZE),
        model=model,
    )


def _frames(path):
    with Image.open(path) as im:
        assert im.is_animated
        out = []
        for i in range(im.n_frames):
            im.seek(i)
            out.append((np.asarray(im.convert("RGB")), im.info["duration"]))
        return im.format, im.info.get("loop"), out


def test_read_sequence_in_frame_order(seq_root):
    frames = read_sequence(seq_root, 1)
    assert [s["json"]["frame"] for s in frames] == list(range(FRAMES))
    assert {s["json"]["sequence"] for s in frames} == {1}
    assert frames[0]["rgb"].shape == (SIZE, SIZE, 3)


def test_video_png_holds_every_frame_in_order_at_the_fps(seq_root, tmp_path):
    out = sequence_video(seq_root, 1, tmp_path / "v.png", scale=2)
    fmt_name, loop, frames = _frames(out)
    assert fmt_name == "PNG" and loop == 0 and len(frames) == FRAMES
    samples = read_sequence(seq_root, 1)
    for (img, duration), sample in zip(frames, samples, strict=True):
        assert duration == pytest.approx(1000 / FPS)
        assert img.shape == (2 * SIZE, 2 * SIZE, 3)
        # Below the caption, frame f is draw_frame of the sequence's frame f (APNG is lossless).
        np.testing.assert_array_equal(img[CAPTION:], np.asarray(draw_frame(sample, 2))[CAPTION:])
    # The caption (frame counter and time) differs from frame to frame.
    assert all((frames[i][0][:CAPTION] != frames[i + 1][0][:CAPTION]).any() for i in range(FRAMES - 1))


def test_video_gif_is_animated_with_centisecond_durations(seq_root, tmp_path):
    out = sequence_video(seq_root, 0, tmp_path / "v.GIF")
    fmt_name, loop, frames = _frames(out)
    assert fmt_name == "GIF" and loop == 0 and len(frames) == FRAMES
    for img, duration in frames:
        assert img.shape == (SIZE, SIZE, 3)
        assert duration == 10 * round(100 / FPS)  # GIF stores 1/100 s: 33.3 ms plays as 30 ms
    assert [p.name for p in tmp_path.iterdir()] == ["v.GIF"]  # no temporary file left


def test_sheet_of_evenly_spaced_frames(seq_root, tmp_path):
    out = sequence_sheet(seq_root, 1, tmp_path / "s.png", count=4, scale=2)
    with Image.open(out) as im:
        assert im.format == "PNG" and not getattr(im, "is_animated", False)
        assert im.size == (4 * (2 * SIZE + 4), 16 + 2 * SIZE + 4)  # frames 0, 2, 3, 5 in one row
        sheet = np.asarray(im.convert("RGB"))
    samples = read_sequence(seq_root, 1)
    for col, f in enumerate((0, 2, 3, 5)):
        x = col * (2 * SIZE + 4)
        tile = sheet[16 + CAPTION : 16 + 2 * SIZE, x : x + 2 * SIZE]
        np.testing.assert_array_equal(tile, np.asarray(draw_frame(samples[f], 2))[CAPTION:])
    with Image.open(sequence_sheet(seq_root, 0, tmp_path / "all.png", count=50, columns=3)) as im:
        assert im.size == (3 * (SIZE + 4), 16 + 2 * (SIZE + 4))  # all six frames, two rows of three


@pytest.mark.parametrize(
    ("sequence", "match"),
    [(2, r"ds: no sequence 2 \(it holds sequences 0 \.\. 1\)"), (-1, "ds: no sequence -1")],
)
def test_no_such_sequence(seq_root, tmp_path, sequence, match):
    with pytest.raises(ValueError, match=match):
        sequence_video(seq_root, sequence, tmp_path / "v.gif")
    with pytest.raises(ValueError, match=match):
        sequence_sheet(seq_root, sequence, tmp_path / "s.png")
    assert not list(tmp_path.iterdir())


def test_bad_suffix_and_not_a_sequence_dataset(seq_root, tmp_path, model):
    with pytest.raises(ValueError, match=r"v\.mp4: the video's suffix must be \.gif or \.png"):
        sequence_video(seq_root, 0, tmp_path / "v.mp4")
    single = make_dataset(tmp_path / "single", num=2, shard_size=2, size=(48, 40), model=model)
    with pytest.raises(ValueError, match="single: not a sequence dataset"):
        sequence_video(single, 0, tmp_path / "v.gif")
    with pytest.raises(ValueError, match="empty: no shards"):
        sequence_sheet(tmp_path / "empty", 0, tmp_path / "s.png")


def test_cli_preview_video_and_sheet(seq_root, tmp_path, capsys):
    video, sheet = tmp_path / "v.gif", tmp_path / "s.png"
    args = ["preview", str(seq_root), "--sequence", "1", "--video", str(video), "--sheet", str(sheet)]
    assert main([*args, "--count", "3", "--scale", "2"]) == 0
    assert capsys.readouterr().out.split() == [str(video), str(sheet)]
    with Image.open(video) as im:
        assert im.n_frames == FRAMES and im.size == (2 * SIZE, 2 * SIZE)
    with Image.open(sheet) as im:
        assert im.size == (3 * (2 * SIZE + 4), 16 + 2 * SIZE + 4)
    # The dataset's usual contact sheet (four tiles per sample, scale 2) still works on frames.
    assert main(["preview", str(seq_root), "--out", str(tmp_path / "c.png"), "--count", "2"]) == 0
    with Image.open(tmp_path / "c.png") as im:
        assert im.size == (4 * 2 * SIZE + 6, 2 * (2 * SIZE + 4))


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--video", "v.gif"], "--video and --sheet need --sequence S"),
        (["--sequence", "0"], "--video and --sheet need --sequence S"),
        ([], "preview needs --out PNG"),
        (["--sequence", "7", "--video", "v.gif"], "ds: no sequence 7"),
    ],
)
def test_cli_preview_bad_input(seq_root, tmp_path, capsys, monkeypatch, extra, message):
    monkeypatch.chdir(tmp_path)
    assert main(["preview", str(seq_root), *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("synth: error: ") and message in err and len(err.strip().splitlines()) == 1
