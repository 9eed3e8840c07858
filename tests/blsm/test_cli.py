from __future__ import annotations

import subprocess
import sys

import pytest

from blsm.cli import main


def test_info_prints_the_summary(capsys):
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    assert "pose atoms:  47" in out and "knee_l.flex" in out and "bone-length variance" in out


def test_bad_model_file_is_a_one_line_error_and_non_zero_exit(tmp_path):
    res = subprocess.run(
        [sys.executable, "-m", "blsm.cli", "info", "--model", str(tmp_path / "nope.npz")],
        capture_output=True, text=True,
    )
    assert res.returncode == 2
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "nope.npz" in lines[0] and lines[0].startswith("blsm: error:")


def test_demo_writes_no_output_on_bad_model(tmp_path):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--model", str(tmp_path / "x.npz"), "--n", "2"]) == 2
    assert not (out / "contact_sheet.png").exists()


@pytest.fixture
def variant():
    from blsm.mitsuba_util import choose_variant

    try:
        return choose_variant()
    except RuntimeError as exc:
        pytest.skip(f"no Mitsuba variant can run here: {exc}")


def test_atoms_and_demo_write_images(tmp_path, variant):
    from PIL import Image

    assert main(["atoms", "--out", str(tmp_path), "--tile", "48x64", "--spp", "4"]) == 0
    atoms = Image.open(tmp_path / "atoms.png")
    assert atoms.size[0] == 12 * 48 and atoms.size[1] >= 8 * 64  # 94 tiles in 12 columns
    assert (tmp_path / "components.png").exists()
    assert main(["demo", "--out", str(tmp_path / "d"), "--n", "4", "--tile", "64x96", "--spp", "4"]) == 0
    sheet = Image.open(tmp_path / "d" / "contact_sheet.png")
    assert sheet.size == (4 * 64, 96)
    assert (tmp_path / "d" / "params.json").exists()
