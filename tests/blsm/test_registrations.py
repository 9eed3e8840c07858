"""Tests of blsm/learn/registration/registrations.py: registration files and the two readers."""

from __future__ import annotations

import json

import numpy as np
import pytest

from blsm.learn.registration.registrations import (
    Registration,
    correspondence_error,
    load_registration,
    load_registration_set,
    load_registrations,
    save_registration,
)


def test_registration_round_trip(tmp_path):
    v = np.random.default_rng(0).random((10, 3)).astype(np.float32)
    reg = Registration(v, np.ones(20, np.float32), np.zeros(47, np.float32), np.zeros(3, np.float32),
                         np.ones(3, np.float32), v * 0.1, {"scan": "a", "error_mean_mm": 1.5})
    path = save_registration(reg, tmp_path / "r.npz")
    back = load_registration(path)
    for k in ("vertices", "bone_scales", "angles", "global_orient", "transl", "displacement"):
        np.testing.assert_array_equal(getattr(back, k), getattr(reg, k))
    assert back.meta == reg.meta
    np.savez(tmp_path / "bad.npz", format=np.array("blsm-scan"))
    with pytest.raises(ValueError, match="bad.npz: not a BLSM registration"):
        load_registration(tmp_path / "bad.npz")
    with pytest.raises(ValueError, match="shape"):
        save_registration(Registration(v, np.ones(20), np.zeros(47), np.zeros(3), np.zeros(3), v[:5]), tmp_path / "x.npz")
    with pytest.raises(ValueError, match="gt_points"):
        correspondence_error(reg, v[:4])


def test_load_registrations_expands_folders_in_order(tmp_path):
    v = np.zeros((4, 3), np.float32)
    for name in ("b", "a"):
        reg = Registration(v, np.ones(2, np.float32), np.zeros(47, np.float32), np.zeros(3, np.float32),
                           np.zeros(3, np.float32), v, {"scan": name})
        save_registration(reg, tmp_path / "regs" / f"{name}.npz")
    regs = load_registrations([tmp_path / "regs"])
    assert [r.meta["scan"] for r in regs] == ["a", "b"]
    assert [r.meta["scan"] for r in load_registrations([tmp_path / "regs" / "b.npz"])] == ["b"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no registration files"):
        load_registrations([tmp_path / "empty"])
    with pytest.raises(ValueError, match="no such registration file"):
        load_registrations([tmp_path / "missing.npz"])


def test_bad_registration_files(model, tmp_path):
    with pytest.raises(ValueError, match="not a folder"):
        load_registration_set(tmp_path / "missing", model.num_vertices)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no .npz"):
        load_registration_set(tmp_path / "empty", model.num_vertices)
    (tmp_path / "bad").mkdir()
    np.savez(tmp_path / "bad" / "r.npz", vertices=np.zeros((5, 3), np.float32))
    with pytest.raises(ValueError, match="r.npz"):
        load_registration_set(tmp_path / "bad", model.num_vertices)
    (tmp_path / "bad2").mkdir()
    np.savez(tmp_path / "bad2" / "q.npz", faces=np.zeros((5, 3)))
    with pytest.raises(ValueError, match="q.npz: missing array 'vertices'"):
        load_registration_set(tmp_path / "bad2", model.num_vertices)
    (tmp_path / "bad3").mkdir()
    np.savez(tmp_path / "bad3" / "s.npz", vertices=model.template.numpy(),
             meta=np.array(json.dumps({"split": "validation"})))
    with pytest.raises(ValueError, match="s.npz: split"):
        load_registration_set(tmp_path / "bad3", model.num_vertices)
    # The strict reader refuses what the set reader takes (no format, no skeleton).
    with pytest.raises(ValueError, match="r.npz: not a BLSM registration file"):
        load_registration(tmp_path / "bad" / "r.npz")
    (tmp_path / "ok").mkdir()
    np.savez(tmp_path / "ok" / "p.npz", vertices=np.zeros((model.num_vertices, 3), np.float32),
             meta=np.array(json.dumps({"subject": "s", "split": "train"})))
    assert load_registration_set(tmp_path / "ok", model.num_vertices).subjects == ["s"]
