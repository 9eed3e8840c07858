"""What a new user meets first (issue 53): the video config without a motion library, what ``--num``
counts, and the lines a run prints before its first image."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from synth import generate as gen
from synth.cli import main
from synth.config import GeneratorConfig, SubjectsConfig

ROOT = Path(__file__).resolve().parents[2]
VIDEO = ROOT / "configs/synth/video.yaml"


@pytest.mark.parametrize("made", [False, True], ids=["absent", "empty"])
def test_the_video_config_without_its_motion_library_names_the_fix(tmp_path, capsys, made):
    out = tmp_path / "video"
    absent = tmp_path / "motions"
    if made:  # a folder with no clips in it (an import that was stopped before its first clip)
        absent.mkdir()
    assert main(["generate", str(VIDEO), "--out", str(out), "--set", f"poses.library={absent}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"synth: error: {absent}: no motion library"), err
    assert "make motions" in err[0] and "poses.library" in err[0], err
    assert ("no motion files" in err[0]) == made, err
    assert not out.exists() and absent.exists() == made


def test_num_says_images_or_sequences_as_the_config_makes_them(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["generate", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "--num NUM how many to make" in help_text and "images, or sequences" in help_text, help_text
    out = tmp_path / "ds"
    assert main(["generate", str(VIDEO), "--out", str(out), "--num", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    frames = 60  # configs/synth/video.yaml's sequence.frames
    assert err == [f"synth: error: --num: the number of sequences of {frames} frames this config makes must be positive, got 0"]
    assert main(["generate", "-", "--out", str(out), "--num", "0"]) == 2
    assert "the number of images" in capsys.readouterr().err
    assert not out.exists()


def test_subjects_are_announced_before_the_first_and_counted_k_of_n(model, tmp_path, capsys, monkeypatch):
    made: list[str] = []

    def fake_subject(model, name, rng, *args, **kwargs):  # the slow step (15-50 s a subject), stood in for
        made.append(name)
        return SimpleNamespace(meta={"height_m": 1.7, "registration": {"fit_mean_mm": 3.0}})

    monkeypatch.setattr(gen, "anny_subject", fake_subject)
    monkeypatch.setattr(gen, "save_subject", lambda s, path: path.write_bytes(b"subject") and path)
    cfg = GeneratorConfig(subjects=SubjectsConfig(count=3))
    (tmp_path / gen.SUBJECTS).mkdir()
    gen.prepare_subjects(cfg, tmp_path, model)
    lines = capsys.readouterr().err.splitlines()
    assert made == ["anny_0000", "anny_0001", "anny_0002"]
    assert lines[0].startswith(f"[synth] making 3 of 3 subjects in {tmp_path / gen.SUBJECTS}"), lines
    assert [line.split()[:3] for line in lines[1:]] == [
        ["[synth]", "subject", f"{k}/3"] for k in (1, 2, 3)
    ], lines


def test_a_terminal_gets_a_line_before_the_generator_loads(tmp_path, capsys, monkeypatch):
    """The first line comes before torch, Mitsuba and BLSM are imported (seconds on a cold start);
    only on a terminal, so that a refused run stays one line in a log."""
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    bad = tmp_path / "bad.yaml"
    bad.write_text("num: 0\n")
    assert main(["generate", str(bad), "--out", str(tmp_path / "ds")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0] == f"[synth] {tmp_path / 'ds'}: loading the generator and checking {bad}", err
    assert err[1].startswith(f"synth: error: {bad}: "), err
