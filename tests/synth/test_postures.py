"""synth.postures: seated legs and arms over their range change only their own atoms and stay in
the limits; the seat carries the person without entering the body; a run with both options
validates, and with both off the generator's draws are the ones it made before."""

from __future__ import annotations

import dataclasses
import math
import shutil

import numpy as np
import pytest
import torch
from tiny_run import TINY

from blsm.joint_limits import angles_from_unconstrained, unconstrained_from_angles
from synth.config import GeneratorConfig, PosesConfig
from synth.postures import seat_under, seated_angles, uniform_arm, vary


def _angles(model, x):
    return angles_from_unconstrained(torch.as_tensor(x, dtype=torch.float64)[None], model.dof_table.limits_tensor())[0].numpy()


def _posed(model, x):
    with torch.no_grad():
        out = model(pose=torch.as_tensor(x, dtype=torch.float32)[None])
    v, j = out.vertices[0].numpy().astype(np.float64), out.joints[0].numpy().astype(np.float64)
    lift = np.array([0.0, v[:, 1].min(), 0.0])  # feet on the ground, as the generator places people
    return v - lift, j - lift


def test_seated_angles_and_arms_change_only_their_atoms(model):
    names, limits = model.dof_names, model.dof_table.limits_tensor().numpy()
    rng = np.random.default_rng(0)
    theta = np.zeros(len(names))
    legs = seated_angles(theta, names, limits, rng)
    changed = {names[i] for i in np.flatnonzero(legs != theta)}
    assert changed <= {f"{j}_{s}.{m}" for s in "lr" for j, m in (("hip", "flex"), ("hip", "abduct"), ("hip", "rotate"),
                                                               ("knee", "flex"), ("ankle", "plantarflex"))}
    for s in "lr":
        assert math.radians(55) <= legs[names.index(f"hip_{s}.flex")] <= math.radians(115)
        assert legs[names.index(f"knee_{s}.flex")] >= math.radians(20)
    assert (legs >= limits[:, 0]).all() and (legs <= limits[:, 1]).all()
    arm = uniform_arm(theta, names, limits, "r", rng)
    moved = {names[i].split(".")[0] for i in np.flatnonzero(arm != theta)}
    assert moved == {"clavicle_r", "shoulder_r", "elbow_r", "wrist_r"}
    assert (arm >= limits[:, 0]).all() and (arm <= limits[:, 1]).all()


def test_vary_is_the_identity_when_off_and_records_what_it_changed(model):
    x = np.random.default_rng(1).normal(size=47).astype(np.float32) * 0.3
    same, info = vary(x, model, 0.0, 0.0, np.random.default_rng(2))
    assert info == {} and np.array_equal(same, x)
    sat, info = vary(x, model, 1.0, 1.0, np.random.default_rng(2))
    assert info == {"posture": "seated", "arms": ["left", "right"]}
    a, b = _angles(model, x), _angles(model, sat)
    spine = [i for i, n in enumerate(model.dof_names) if n.split(".")[0] in ("spine_01", "spine_02", "spine_03", "neck", "head")]
    np.testing.assert_allclose(a[spine], b[spine], atol=1e-5)  # the trunk stays the prior's


def test_the_seat_carries_a_seated_body_and_not_a_standing_one(model):
    names = model.dof_names
    limits_t = model.dof_table.limits_tensor()
    found = 0
    for seed in range(6):
        rng = np.random.default_rng(seed)
        theta = seated_angles(np.zeros(len(names)), names, limits_t.numpy(), rng)
        x = unconstrained_from_angles(torch.from_numpy(theta)[None], limits_t)[0].numpy()
        v, j = _posed(model, x)
        seat = seat_under(v, j, list(model.bone_names), rng)
        if seat is None:
            continue
        found += 1
        w, h, d = seat.size
        assert 0.2 <= h <= 0.7 and 0.3 <= w <= 0.8 and 0.15 <= d
        # Seat frame: the box's x along its width, z along its depth, y up from the ground.
        c, s = math.cos(seat.yaw), math.sin(seat.yaw)
        rel = v[:, [0, 2]] - np.array(seat.centre)
        lx, lz = rel @ np.array([c, -s]), rel @ np.array([s, c])
        over = (np.abs(lx) <= w / 2) & (np.abs(lz) <= d / 2)
        assert over.sum() > 50  # the buttocks and thighs are over it
        assert v[over, 1].min() >= h - 1e-6  # nothing of the body inside the box
        assert v[over, 1].min() <= h + 1e-6  # and the body rests on its top
    assert found >= 4
    # A body narrower than its hips plus the margin (x squeezed, the joints kept) gets a seat no
    # wider than itself, so the seat stays in its footprint.
    narrow = v * np.array([0.4, 1.0, 1.0])
    seat = seat_under(narrow, j, list(model.bone_names), np.random.default_rng(0))
    assert seat is not None and seat.size[0] / 2 <= np.abs(narrow[:, 0] - seat.centre[0]).max() + 1e-9
    rest = unconstrained_from_angles(torch.zeros(1, len(names), dtype=torch.float64), limits_t)[0].numpy()
    v, j = _posed(model, rest)  # standing (the bind pose)
    assert seat_under(v, j, list(model.bone_names), np.random.default_rng(0)) is None  # standing: no seat


def test_bad_posture_options_are_refused():
    with pytest.raises(ValueError, match="seated_rate"):
        PosesConfig(seated_rate=1.5)
    with pytest.raises(ValueError, match="arms_rate"):
        PosesConfig(arms_rate=-0.1)
    with pytest.raises(ValueError, match="prior or mix"):
        PosesConfig(source="library", library="x", seated_rate=0.5)
    with pytest.raises(ValueError, match="posable pipeline"):
        GeneratorConfig(pipeline="raw", poses=PosesConfig(arms_rate=0.5))
    assert GeneratorConfig(poses=PosesConfig(seated_rate=0.5)).occluder_slots == GeneratorConfig().people.max
    assert GeneratorConfig().occluder_slots == 0


def test_generate_seated_validates_with_seats(tiny, tmp_path):
    """The tiny run with every person seated and every arm drawn over its range (its subjects
    reused): 0 validation failures, a seat per seated person that got one, seats only hide."""
    from synth.dataset.format import decode_sample
    from synth.dataset.shards import read_shard
    from synth.generate import generate
    from synth.validate import validate

    out = tmp_path / "seated"
    out.mkdir()
    shutil.copytree(tiny / "subjects", out / "subjects")
    generate(dataclasses.replace(TINY, poses=PosesConfig(seated_rate=1.0, arms_rate=1.0)), out, progress=False, resume=True)
    rep = validate(out)
    assert rep.samples == TINY.num and rep.failures == []
    seats = 0
    for shard in sorted(out.glob("shard-*.tar")):
        for f in read_shard(shard).values():
            doc = decode_sample(f)["json"]
            motions = [p["motion"] for p in doc["people"]]
            assert all(m["posture"] == "seated" and m["arms"] == ["left", "right"] for m in motions)
            assert len(doc["occluders"]) == sum(m["seat"] for m in motions)
            seats += len(doc["occluders"])
    assert seats >= TINY.num
