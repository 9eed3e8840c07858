"""synth.occluders: closed outward meshes, placed between camera and people without touching them;
their pixels are nobody's and the people's labels are otherwise unchanged."""

from __future__ import annotations

import dataclasses
import math
import shutil

import numpy as np
import pytest
import trimesh
from tiny_run import TINY

from blsm.camera import Camera
from synth.config import GeneratorConfig, OccludersConfig, SequenceConfig
from synth.occluders import (
    KINDS,
    Occluder,
    occluder_faces,
    occluder_mesh,
    occluder_vertex_count,
    place_occluders,
)


@pytest.mark.parametrize("kind", KINDS)
def test_meshes_are_closed_and_face_outwards(kind):
    size = (0.5, 1.2, 0.4) if kind == "box" else (0.5, 1.2, 0.5)  # a cylinder's (radius, height, radius)
    o = Occluder(kind, (1.0, -2.0), size, 0.3, (0.2, 0.3, 0.4), 1)
    v, f, c = occluder_mesh(o)
    assert v.shape == (occluder_vertex_count(kind), 3) and f is occluder_faces(kind) and c.shape == v.shape
    mesh = trimesh.Trimesh(v, f)  # merged vertices: one closed surface
    assert mesh.is_watertight and mesh.volume > 0
    assert np.isclose(v[:, 1].min(), 0.0) and np.isclose(v[:, 1].max(), 1.2)  # on the ground
    expected = 0.5 * 1.2 * 0.4 if kind == "box" else 0.5 * 32 * 0.5**2 * math.sin(2 * math.pi / 32) * 1.2
    assert mesh.volume == pytest.approx(expected, rel=1e-6)


def _camera(at: np.ndarray) -> Camera:
    """A camera at ``at`` looking at the origin, level."""
    z = -at / np.linalg.norm(at)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return Camera(K=np.array([[200.0, 0, 64], [0, 200.0, 64], [0, 0, 1]]), R=R, t=-R @ at, width=128, height=128)


def test_placement_keeps_clear_of_people_and_camera_and_stays_in_front():
    rng = np.random.default_rng(0)
    people = [(np.array([0.0, 0.0]), 0.35), (np.array([1.0, 0.3]), 0.3)]
    cam = _camera(np.array([0.5, 1.6, 5.0]))
    placed = []
    for _ in range(200):
        placed += place_occluders(people, cam, 1.0, 2, 0.1, rng)
    assert len(placed) > 150
    for o in placed:
        c = np.array(o.centre)
        for p, r in people:
            assert np.linalg.norm(c - p) >= r + o.radius + 0.1 - 1e-6
        assert np.linalg.norm(c - np.array([0.5, 5.0])) >= o.radius + 0.6 - 1e-6
        assert c[1] > 0.0  # on the camera's side of the people
        assert Occluder.from_json(o.to_json()) == o
    assert place_occluders(people, cam, 0.0, 2, 0.1, rng) == []


def test_bad_occluders_are_refused():
    with pytest.raises(ValueError, match="kind"):
        Occluder("sphere", (0, 0), (1, 1, 1), 0, (0, 0, 0), 0)
    with pytest.raises(ValueError, match="lacks"):
        Occluder.from_json({"kind": "box"})
    with pytest.raises(ValueError, match="occluders.prob"):
        OccludersConfig(prob=2.0)
    with pytest.raises(ValueError, match="single images"):
        GeneratorConfig(occluders=OccludersConfig(enabled=True), sequence=SequenceConfig(enabled=True))


def test_generate_with_occluders_validates_and_only_hides_people(tiny, tmp_path):
    """The tiny run again with occluders in every sample (its subjects reused): 0 validation
    failures; the people, camera and keypoints are the same, their masks only lose pixels."""
    from synth.dataset.format import decode_sample
    from synth.dataset.shards import read_shard
    from synth.generate import generate
    from synth.validate import validate

    out = tmp_path / "occluded"
    out.mkdir()
    shutil.copytree(tiny / "subjects", out / "subjects")
    generate(dataclasses.replace(TINY, occluders=OccludersConfig(enabled=True, prob=1.0)), out, progress=False, resume=True)
    rep = validate(out)
    assert rep.samples == TINY.num and rep.failures == []

    def samples(d):
        return {k: decode_sample(f) for s in sorted(d.glob("shard-*.tar")) for k, f in read_shard(s).items()}

    plain, occluded = samples(tiny), samples(out)
    hidden = 0
    for k in plain:
        a, b = plain[k], occluded[k]
        assert a["json"]["camera"]["R"] == b["json"]["camera"]["R"] and len(b["json"]["occluders"]) >= 1
        for p, q in zip(a["json"]["people"], b["json"]["people"]):
            assert p["keypoints_2d"] == q["keypoints_2d"]
            assert sum(q["visible"]) <= sum(p["visible"])
        assert not ((b["mask"] > 0) & (b["mask"] != a["mask"])).any()  # nobody gains a pixel
        hidden += int((a["mask"] > 0).sum() - (b["mask"] > 0).sum())
    assert hidden > 0
