from __future__ import annotations

import numpy as np
import pytest
import torch

import blsm
from blsm import io
from blsm.joint_limits import DEFAULT_DOF_TABLE
from blsm.model import DEFAULT_MODEL


def test_packaged_model_embeds_the_dof_table_file():
    data = io.read_model(DEFAULT_MODEL)
    assert data.dof_table_yaml == DEFAULT_DOF_TABLE.read_text()
    # The packaged model is the scan pipeline's output (blsm train, default config).
    assert data.meta["name"] == "blsm-learned"
    assert data.meta["build_command"].startswith("blsm train configs/blsm/train_default.yaml")
    report = data.meta["train_report"]
    assert report["registrations"]["train_rest"] >= 500
    assert 0.9 < report["bone_pca_explained_first3"] <= 1.0


def test_round_trip(tmp_path):
    data = io.read_model(DEFAULT_MODEL)
    path = io.save_model(data, tmp_path / "copy.npz")
    m1, m2 = blsm.load(), blsm.load(path)
    x = torch.randn(2, 47)
    assert torch.equal(m1(pose=x).vertices, m2(pose=x).vertices)


def test_bad_files_raise_naming_the_file(tmp_path):
    with pytest.raises(ValueError, match="missing.npz: no such model file"):
        blsm.load(tmp_path / "missing.npz")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="junk.npz: not a readable"):
        blsm.load(junk)
    data = io.read_model(DEFAULT_MODEL)
    del data.arrays["weights"]
    with pytest.raises(ValueError, match="missing array 'weights'"):
        io.save_model(data, tmp_path / "x.npz")
    assert not (tmp_path / "x.npz").exists()
    data = io.read_model(DEFAULT_MODEL)
    data.arrays["weights"] = data.arrays["weights"] * 2
    with pytest.raises(ValueError, match="sum to 1"):
        io.save_model(data, tmp_path / "x.npz")
    data = io.read_model(DEFAULT_MODEL)
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(ValueError, match="other.npz: not a BLSM model file"):
        blsm.load(tmp_path / "other.npz")
