"""Tests of blsm/learn/cli.py: the learning commands of ``blsm``.

The commands' work is tested with their modules (test_register.py, test_evaluate.py,
test_population.py, test_pipeline.py); here: that they are all reachable and how they fail.
"""

from __future__ import annotations

import pytest

from blsm.cli import build_parser, main
from blsm.learn.cli import HELP

EXAMPLES = {
    "scans": ["make", "--out", "p", "--subjects", "1"],
    "register": ["s.npz", "--out", "o"],
    "learn": ["r", "--out", "m.npz"],
    "train": ["c.yaml", "--out", "m.npz"],
    "evaluate": ["--registrations", "r"],
    "train-smpl": ["--registrations", "r", "--out", "s.npz"],
    "reparam": ["default", "t.obj", "--out", "m.npz"],
    "scan-keypoints": ["s.npz", "--out", "k.json"],
    "train-landmark-detector": ["p", "--out", "d.pt"],
}


def test_every_learning_command_is_a_subcommand_with_its_help_line(capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["--help"])
    assert exc.value.code == 0
    out = " ".join(capsys.readouterr().out.split())
    assert set(EXAMPLES) == set(HELP)
    for name, text in HELP.items():
        assert f"{name} {' '.join(text.split())}" in out
        assert callable(build_parser().parse_args([name, *EXAMPLES[name]]).func)


@pytest.mark.parametrize(
    ("argv", "stream", "message"),
    [
        ("learn {tmp}/none --out {tmp}/m.npz", "err",
         "blsm learn: error: {tmp}/none: no such registration file"),
        ("register {tmp}/s.npz --out {tmp}/o --batch 0", "err", "blsm register: error: --batch must be >= 1"),
        ("register {tmp}/s.npz --out {tmp}/o --landmark-detector {tmp}/d.pt", "err",
         "blsm register: error: {tmp}/d.pt: --landmark-detector needs --detector landmarks"),
        ("train {tmp}/none.yaml --out {tmp}/m.npz", "err", "blsm train: error: {tmp}/none.yaml: cannot read"),
        ("train-smpl --registrations {tmp}/none --out {tmp}/s.npz", "out",
         "blsm train-smpl: error: {tmp}/none: not a folder of registrations"),
        ("evaluate --registrations {tmp}/none --ks x --out {tmp}/e.md", "out",
         "blsm evaluate: error: invalid literal"),
        ("train-landmark-detector {tmp}/none --out {tmp}/d.pt", "err",
         "blsm train-landmark-detector: error: {tmp}/none: not a population folder (no scans/)"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, argv, stream, message):
    assert main(argv.format(tmp=tmp_path).split()) == 2
    captured = capsys.readouterr()
    lines = (captured.err if stream == "err" else captured.out).strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(message.format(tmp=tmp_path)), lines
    assert not list(tmp_path.iterdir())  # nothing written
