"""synth.close and synth.contacts: people placed touching without interpenetrating, with contact
and occupancy labels that the validator recomputes from the rebuilt bodies."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
import trimesh
from tiny_run import TINY

from synth.close import Solid, collides, depth_and_gap, merge_seats, turn_to
from synth.config import CloseConfig, GeneratorConfig, LabelsConfig, PeopleConfig, SequenceConfig
from synth.occluders import Occluder


def _cube(centre, side=0.5) -> Solid:
    m = trimesh.creation.box(extents=(side, side, side))
    v = np.asarray(m.vertices) + centre
    pts = trimesh.sample.sample_surface_even(m, 4000, seed=0)[0] + centre
    return Solid(v, np.asarray(m.faces), np.concatenate([v, pts]))


def test_inside_depth_and_resolution_of_two_cubes():
    from synth.close import STEP_M, ClosePlacer

    a, b = _cube(np.zeros(3)), _cube(np.zeros(3))
    # b moved 0.4 along x: its corners 0.1 deep in a, and a's corners 0.1 deep in b.
    assert depth_and_gap(a, b.moved(np.array([0.4, 0.0, 0.0]))) == pytest.approx((0.1, 0.0), abs=1e-9)
    assert depth_and_gap(a, b.moved(np.array([0.55, 0.0, 0.0]))) == pytest.approx((0.0, 0.05), abs=1e-9)
    for d, want in ((0.4, True), (0.497, True), (0.499, False), (0.55, False)):  # the grid and the exact test
        assert collides(a, b, np.array([d, 0.0, 0.0]), 0.002) is want
    placer = ClosePlacer(CloseConfig(tolerance=0.002), [], [])
    off, tests = placer.resolve([(a, b)], np.array([0.1, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    assert 0.498 - STEP_M <= off[0] <= 0.5 and tests < 20  # just touching, within the tolerance
    assert depth_and_gap(a, b.moved(off))[0] <= 0.002 and depth_and_gap(a, b.moved(off))[1] < STEP_M
    # A start that is free is brought in until it would touch.
    off, _ = placer.resolve([(a, b)], np.array([1.2, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    assert off[0] == pytest.approx(0.499, abs=0.002)


def test_turn_to_faces_the_asked_way():
    from synth.camera import facing_yaw_deg

    orient = np.array([0.1, 0.7, -0.2], np.float32)
    for yaw in (-170.0, -30.0, 0.0, 95.0):
        assert facing_yaw_deg(turn_to(orient, yaw)) == pytest.approx(yaw, abs=1e-3)


def test_two_seats_make_one_bench():
    a = Occluder("box", (0.0, 0.0), (0.5, 0.45, 0.4), 0.0, (0.5, 0.5, 0.5), 1)
    b = Occluder("box", (0.55, 0.05), (0.5, 0.455, 0.4), 0.02, (0.5, 0.5, 0.5), 2)
    bench = merge_seats(a, b)
    assert bench is not None and bench.size[0] == pytest.approx(1.05, abs=0.01) and bench.size[1] == 0.45
    assert merge_seats(a, dataclasses.replace(b, size=(0.5, 0.5, 0.4))) is None  # 5 cm higher
    assert merge_seats(a, dataclasses.replace(b, yaw=0.5)) is None  # turned


def test_bad_close_configs_are_refused():
    with pytest.raises(ValueError, match="apart or close"):
        PeopleConfig(placement="near")
    with pytest.raises(ValueError, match="weights"):
        CloseConfig(side=0, facing=0, hands=0, shoulder=0, seated=0)
    with pytest.raises(ValueError, match="single images"):
        GeneratorConfig(people=PeopleConfig(placement="close"), sequence=SequenceConfig(enabled=True),
                        poses=dataclasses.replace(GeneratorConfig().poses, source="library", library="motions"))
    with pytest.raises(ValueError, match="contact_distance"):
        LabelsConfig(contact_distance=-0.01)


def test_default_manifests_hold_no_new_key():
    from synth.generate import cfg_json

    d = cfg_json(TINY)
    assert "labels" not in d and "placement" not in d["people"] and "close" not in d["people"]
    d = cfg_json(dataclasses.replace(TINY, labels=LabelsConfig(contact_distance=0.02)))
    assert d["labels"] == {"topology": "", "topology_name": "topo2", "contact_distance": 0.02}


CLOSE = dataclasses.replace(
    TINY, num=6, people=PeopleConfig(min=2, max=2, placement="close", close=CloseConfig(seated=2.0)),
    labels=LabelsConfig(contact_distance=0.02, occupancy=64))


@pytest.fixture(scope="module")
def close_run(tiny, tmp_path_factory):
    from synth.generate import generate

    out = tmp_path_factory.mktemp("close") / "run"
    out.mkdir()
    shutil.copytree(tiny / "subjects", out / "subjects")
    generate(CLOSE, out, progress=False, resume=True)
    return out


def _samples(d):
    from synth.dataset.format import decode_sample
    from synth.dataset.shards import read_shard

    return {k: decode_sample(f) for s in sorted(d.glob("shard-*.tar")) for k, f in read_shard(s).items()}


def test_close_run_touches_validates_and_loads(close_run):
    from synth.dataset.images import SynthDataset
    from synth.validate import validate

    rep = validate(close_run)
    assert rep.samples == CLOSE.num and rep.failures == []
    samples = _samples(close_run)
    gaps = []
    for s in samples.values():
        doc = s["json"]
        pl = doc["placement"]
        assert pl["arrangement"] in ("side", "facing", "hands", "shoulder", "seated") and len(pl["pairs"]) == 1
        pair = pl["pairs"][0]
        assert pair["depth_mm"] <= 1000 * CLOSE.people.close.tolerance + 1e-6
        gaps.append(pair["gap_mm"])
        (c,) = doc["contacts"]
        assert c["people"] == [0, 1] and c["distance"] == 0.02
        assert c["closest_mm"] >= -1000 * CLOSE.people.close.tolerance - 1e-6
        assert s["occupancy"].shape == (2, 64, 4) and 0 < s["occupancy"][..., 3].mean() < 1
    assert np.median(gaps) < 5.0  # millimetres: they touch
    assert sum(bool(s["json"]["contacts"][0]["vertices"][0]) for s in samples.values()) >= CLOSE.num - 1
    ds = SynthDataset(close_run, crop=32)
    item = ds[0]
    assert item["contact_parts"].shape == (6,) and item["occupancy"].shape == (64, 4)
    assert ds.contacts(0)[0]["with"] == 1 - int(item["person"])


def test_validate_finds_wrong_contacts_and_occupancy(close_run, tmp_path):
    """The same run with one contact vertex dropped and one occupancy flag flipped: both found."""
    from synth.dataset import format as fmt
    from synth.dataset.shards import read_shard, write_shard
    from synth.validate import validate

    bad = tmp_path / "bad"
    shutil.copytree(close_run, bad)
    man = json.loads((bad / "manifest.json").read_text())
    name = sorted(man["shards"])[0]
    samples = read_shard(bad / name)
    key = sorted(samples)[0]
    f = samples[key]
    doc = fmt.decode_json(f["json"])
    c = doc["contacts"][0]
    c["vertices"][0] = c["vertices"][0][1:] if c["vertices"][0] else [0]
    f["json"] = fmt.encode_json(doc)
    occ = fmt.decode_npy_gz(f["occupancy.npy.gz"])
    occ[0, 0, 3] = 1.0 - occ[0, 0, 3]
    f["occupancy.npy.gz"] = fmt.encode_npy_gz(occ)
    man["shards"][name]["sha256"] = write_shard(bad / name, [(int(k), x) for k, x in sorted(samples.items())])
    (bad / "manifest.json").write_text(json.dumps(man))
    msgs = " | ".join(validate(bad).failures)
    assert "contacts 0-1" in msgs and "occupancy.npy.gz person 0: 1 of 64 points flagged wrongly" in msgs
