"""The worker's side of a run (synth/worker.py): failures returned as data, a sequence's frames
made together and served in order, the work unit of each kind of run."""

from __future__ import annotations

import dataclasses

import pytest

from synth import worker
from synth.config import GeneratorConfig, PosesConfig, SequenceConfig


class _Sequences:
    """Stands in for synth.sequence.SequenceMaker."""

    def __init__(self, maker: _Maker) -> None:
        self.frames, self.fail, self.made = maker.cfg.sequence.frames, maker.fail_sequences, []
        maker.seqs = self

    def make(self, seq, rng):
        self.made.append(seq)
        if self.fail:
            raise ValueError("clip.bvh: a bad clip\nmore detail")
        return [{"frame": f"{seq}/{f}".encode()} for f in range(self.frames)]


class _Maker:
    """Stands in for synth.sample.SampleMaker."""

    def __init__(self, cfg: GeneratorConfig, fail_at: int = -1, fail_sequences: bool = False) -> None:
        self.cfg, self.fail_at, self.fail_sequences = cfg, fail_at, fail_sequences
        self.seqs: _Sequences | None = None

    def make(self, index, rng):
        if index == self.fail_at:
            raise RuntimeError("simulated failure")
        return {"index": str(index).encode()}


@pytest.fixture
def maker(monkeypatch):
    def install(cfg: GeneratorConfig, **kw) -> _Maker:
        m = _Maker(cfg, **kw)
        monkeypatch.setattr(worker, "_MAKER", m)
        monkeypatch.setattr(worker, "_SEQUENCE", (-1, None))
        monkeypatch.setattr(worker, "_SEQUENCES", None)
        monkeypatch.setattr(worker, "SequenceMaker", _Sequences)
        return m

    return install


def _video(frames: int = 4) -> GeneratorConfig:
    return dataclasses.replace(GeneratorConfig(), poses=PosesConfig(source="library", library="clips"),
                               sequence=SequenceConfig(enabled=True, frames=frames))


def test_a_unit_of_work_is_an_image_or_a_sequence():
    assert worker.frames_per_sample(GeneratorConfig()) == 1
    assert worker.frames_per_sample(_video(6)) == 6


def test_a_failed_sample_is_returned_as_data(maker):
    maker(GeneratorConfig(), fail_at=3)
    assert worker.make_one(2) == (2, {"index": b"2"}, "", "")
    assert worker.make_one(3) == (3, None, "RuntimeError", "simulated failure")


def test_a_sequence_is_made_once_and_its_frames_served_in_order(maker):
    m = maker(_video(4))
    out = worker.make_sequence(1)
    assert [r[0] for r in out] == [4, 5, 6, 7]
    assert [r[1]["frame"] for r in out] == [b"1/0", b"1/1", b"1/2", b"1/3"]
    assert worker.make_one(6)[1] == {"frame": b"1/2"} and m.seqs.made == [1]


def test_every_frame_of_a_failed_sequence_reports_its_one_line(maker):
    m = maker(_video(3), fail_sequences=True)
    out = [worker.make_one(i) for i in range(3)]
    assert out == [(i, None, "ValueError", "clip.bvh: a bad clip") for i in range(3)] and m.seqs.made == [0]


def test_a_worker_makes_nothing_before_it_is_set_up(monkeypatch):
    monkeypatch.setattr(worker, "_MAKER", None)
    for call in (worker.make_one, worker.make_sequence, worker.make_in_process):
        with pytest.raises(RuntimeError, match="before init_worker"):
            call(0)


def test_errors_are_one_line_or_their_type():
    assert worker.format_error(ValueError("first\nsecond")) == "first"
    assert worker.format_error(KeyError()) == "KeyError"
