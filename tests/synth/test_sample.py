"""A worker's sample maker (synth/sample.py): posing as validate rebuilds it, placement, kernels
compiled once per worker, the people's window, midpoint subdivision, distinct people in an image."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tiny_run import TINY, drawing_maker, drawn

from synth.config import GeneratorConfig, PeopleConfig, RenderConfig
from synth.dataset import format as fmt
from synth.dataset.shards import sample_rng
from synth.people import place_people
from synth.sample import Person, SampleMaker, pose_person, subdivide

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def maker(tiny) -> SampleMaker:
    """A maker over the tiny dataset's subjects (no scene is built until a sample is made)."""
    return SampleMaker(TINY, tiny, "scalar_rgb", threads=1)


def _pose(maker: SampleMaker, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    x, orient, _ = maker.poses.sample(np.random.default_rng(seed))
    return x, orient, np.array([0.3, 0.0, -0.2], np.float32)


def test_the_makers_posing_is_pose_person_with_the_rigs_hair(maker):
    """validate.MeshRebuilder rebuilds people with pose_person: it must be what the maker renders."""
    x, orient, transl = _pose(maker)
    p = maker.pose(1, x, orient, transl)
    rig = maker.rig(1)
    assert p.si == 1 and p.rig is rig and rig.hair is not None and rig.parents is None
    q = pose_person(maker.subjects[1], maker.model, TINY.pipeline, x, orient, transl, None, rig.hair)
    for name in ("vertices", "faces", "vertex_bones", "keypoints", "joints", "angles", "transforms", "pose",
                 "global_orient", "transl", "bone", "shape", "hair"):
        assert np.array_equal(getattr(p, name), getattr(q, name)), name
    assert p.subject == q.subject == maker.subjects[1].id
    assert len(p.vertices) == len(p.vertex_bones) and p.hair.shape[1] == 3


def test_a_moved_person_moves_as_one_and_its_shell_holds_the_hair(maker):
    p = maker.pose(0, *_pose(maker, 1))
    before = {k: getattr(p, k).copy() for k in ("vertices", "keypoints", "joints", "hair", "transl")}
    d = np.array([1.0, 0.25, -2.0])
    p.move(d)
    for k, v in before.items():
        assert getattr(p, k).dtype == np.float32, k
        np.testing.assert_allclose(getattr(p, k), v + d, atol=1e-5, err_msg=k)
    assert np.array_equal(p.shell(), np.concatenate([p.vertices, p.hair]))
    bare = dataclasses.replace(p, hair=None)
    assert bare.shell() is bare.vertices


def test_a_subdivided_person_has_a_bone_and_faces_for_every_new_vertex(maker):
    m = maker.model
    parents, faces = subdivide(m.faces.numpy())
    x, orient, transl = _pose(maker, 2)
    whole = pose_person(maker.subjects[0], m, "blsm", x, orient, transl)
    p = pose_person(maker.subjects[0], m, "blsm", x, orient, transl, (parents, faces))
    assert len(p.vertices) == len(parents) == len(p.vertex_bones) and p.faces is faces
    np.testing.assert_array_equal(p.vertices[: len(whole.vertices)], whole.vertices)
    np.testing.assert_array_equal(p.vertex_bones, whole.vertex_bones[parents[:, 0]])
    assert p.hair is None and isinstance(p, Person)


def test_placed_people_keep_their_gap():
    rng = np.random.default_rng(3)
    feet = [(rng.uniform(-1, 1, 2), float(rng.uniform(0.2, 0.5))) for _ in range(6)]
    offsets = place_people(feet, 0.1, rng)
    centres = [c + o[[0, 2]] for (c, _), o in zip(feet, offsets, strict=True)]
    assert all(o[1] == 0.0 for o in offsets)
    for i in range(len(feet)):
        for j in range(i):
            assert np.linalg.norm(centres[i] - centres[j]) >= feet[i][1] + feet[j][1] + 0.1 - 1e-9


def test_a_warm_worker_compiles_no_kernel_for_new_samples(tiny):
    """Issue 34: after its first samples, a worker making new samples (new people count, pose,
    camera, window, sky, seed) launches only kernels it has compiled already: Dr.Jit's kernel
    history shows every JIT kernel as an in-memory cache hit. 128 px, so the people's window is
    traced (its offset and size are the kernel's data, not literals) and shadows are on; one or
    two people (one scene of two slots)."""
    import drjit as dr

    from blsm.mitsuba_util import resolve_variant
    from synth.dataset.shards import sample_rng

    cfg = dataclasses.replace(TINY, camera=dataclasses.replace(TINY.camera, width=128, height=128))
    assert cfg.ground.shadows and cfg.hair.enabled
    maker = SampleMaker(cfg, tiny, resolve_variant(None), threads=0)
    for i in (1000, 1001):  # warm-up: the first sample compiles every kernel
        maker.make(i, sample_rng(cfg.seed, i))
    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # clears it
        people, windows = set(), set()
        for i in range(2000, 2008):
            doc = fmt.decode_sample(maker.make(i, sample_rng(cfg.seed, i)))["json"]
            people.add(len(doc["people"]))
            windows.add(tuple(np.round(np.asarray(doc["people"][0]["box_full"]))))
        history = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was)
    assert people == {1, 2} and len(windows) == 8  # the samples do vary what used to compile
    jit = [k for k in history if k["type"] == dr.KernelType.JIT]
    assert len(jit) >= 8 * 3  # path tracer, label pass and shadow catcher, per sample at least
    # In memory: neither compiled now nor loaded from Dr.Jit's disk cache (which another process,
    # or an earlier run over these samples, may have filled).
    new = [(k["hash"], k["size"]) for k in jit if not k["cache_hit"] or k["cache_disk"]]
    assert new == [], f"{len(new)} kernels compiled or loaded for new samples"


def test_rendering_only_the_peoples_window_keeps_the_labels_and_the_image(tiny):
    """With the backdrop composited (shadows, the default), the path tracer traces only the
    people's window (SampleMaker.windowed): the same sample made both ways has the same labels, and
    the image agrees up to Monte Carlo noise (another random stream for the people; the shadow
    catcher skips the pixels a person covers fully, which the noise moves by a few)."""
    from blsm.mitsuba_util import resolve_variant
    from synth.dataset.shards import sample_rng

    cfg = dataclasses.replace(TINY, render=RenderConfig(spp=36))
    made = {}
    for name, windowed in (("window", True), ("whole", False)):
        maker = SampleMaker(cfg, tiny, resolve_variant(None), threads=0)
        maker.windowed = windowed
        made[name] = [fmt.decode_sample(maker.make(1, sample_rng(cfg.seed, 1)))]
    for a, b in zip(made["window"], made["whole"], strict=True):
        for count in ("ground_pixels", "shadowed_pixels"):
            n = [d["background"]["ground"].pop(count) for d in (a["json"], b["json"])]
            assert abs(n[0] - n[1]) <= 0.05 * max(n), (count, n)
        assert a["json"] == b["json"]
        for key in ("mask", "parts", "depth"):
            assert np.array_equal(a[key], b[key]), key
        rgb_a, rgb_b = a["rgb"].astype(np.float64), b["rgb"].astype(np.float64)
        person = a["mask"] > 0
        assert person.sum() > 200 and (~person).sum() > 200
        assert np.abs(rgb_a - rgb_b)[~person].mean() < 0.5  # 8-bit levels: the composited backdrop
        assert abs(rgb_a[person].mean() - rgb_b[person].mean()) < 1.5
        assert np.sqrt(np.mean((rgb_a - rgb_b) ** 2)) < 6.0


def test_subdivision_keeps_each_child_inside_its_parent():
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    parents, new = subdivide(faces)
    assert new.shape == (8, 3) and parents.shape == (4 + 5, 2)
    verts = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    sub = 0.5 * (verts[parents[:, 0]] + verts[parents[:, 1]])
    for f in range(len(faces)):
        tri = verts[faces[f]]
        for c in new[4 * f : 4 * f + 4]:
            centroid = sub[c].mean(0)
            e1, e2 = tri[1] - tri[0], tri[2] - tri[0]
            b = np.linalg.lstsq(np.stack([e1, e2], 1), centroid - tri[0], rcond=None)[0]
            assert b.min() >= 0 and b.sum() <= 1


def test_the_people_of_one_image_are_distinct_subjects(tiny):
    """Issue 53: with a pool of 8 subjects, the two or three people of an image are as many
    subjects (drawn without replacement), and a sample's draw is still its ``(seed, index)``'s."""
    cfg = dataclasses.replace(TINY, people=PeopleConfig(min=2, max=3))
    m = drawing_maker(cfg, tiny, pool=8)
    draws = [drawn(m.make, i, sample_rng(cfg.seed, i)) for i in range(32)]
    twins = {i: d for i, d in enumerate(draws) if len(set(d)) < len(d)}
    assert twins == {}, f"the same subject twice in one image: {twins}"
    assert {len(d) for d in draws} == {2, 3} and {s for d in draws for s in d} == set(range(8))
    again = drawing_maker(cfg, tiny, pool=8)
    assert [drawn(again.make, i, sample_rng(cfg.seed, i)) for i in (30, 5)] == [draws[30], draws[5]]


def test_distinct_draws_change_only_the_images_that_had_a_twin(tiny):
    """``people.distinct: false`` draws with replacement, as before the key; the default redraws
    only a repeated subject, so an image whose people were distinct before is drawn as before."""
    cfg = dataclasses.replace(TINY, people=PeopleConfig(min=2, max=3, distinct=False))
    old_maker = drawing_maker(cfg, tiny, pool=8)
    old = [drawn(old_maker.make, i, sample_rng(cfg.seed, i)) for i in range(24)]
    new_maker = drawing_maker(dataclasses.replace(cfg, people=PeopleConfig(min=2, max=3)), tiny, pool=8)
    new = [drawn(new_maker.make, i, sample_rng(cfg.seed, i)) for i in range(24)]
    had_twin = [len(set(d)) < len(d) for d in old]
    assert any(had_twin)
    assert all(n == o for n, o, t in zip(new, old, had_twin, strict=True) if not t)
    assert all(len(set(n)) == len(n) for n in new)


def test_a_pool_smaller_than_the_people_warns_once_and_uses_every_subject(tiny, model, capsys):
    """Three people from two subjects: one line before any work (not one per sample or worker), and
    each image shows both subjects before it shows one twice."""
    from synth.generate import check_inputs

    few = dataclasses.replace(TINY, people=PeopleConfig(min=3, max=3))  # TINY has 2 subjects
    check_inputs(few, model)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "people.max = 3" in err[0] and "2 subjects" in err[0], err
    check_inputs(TINY, model)  # 2 subjects for at most 2 people: nothing to say
    assert capsys.readouterr().err == ""
    m = drawing_maker(few, tiny, pool=2)
    draws = [drawn(m.make, i, sample_rng(few.seed, i)) for i in range(12)]
    assert all(len(d) == 3 and sorted(set(d)) == [0, 1] for d in draws), draws


def test_distinct_people_from_too_few_subjects_is_a_one_line_error_that_writes_nothing(tmp_path):
    out = tmp_path / "o"
    sets = ["subjects.count=2", "people.max=3", "people.distinct=true"]
    cmd = [sys.executable, "-m", "synth.cli", "generate", "-", "--out", str(out)]
    cmd += [x for s in sets for x in ("--set", s)]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0, r.stderr
    assert r.stderr.startswith("synth: error: people.distinct") and "2 subjects" in r.stderr, r.stderr
    assert "people.max = 3" in r.stderr, r.stderr
    assert not out.exists()


def test_a_dataset_drawn_before_distinct_people_is_not_resumed_with_the_new_draws(tmp_path):
    """The manifest records ``people.distinct`` where the draws changed (several people), so
    ``--resume`` refuses a dataset made before it rather than mixing old and new draws; one-person
    datasets keep the manifests of before. Workers rebuild the config from the manifest's."""
    from synth.config import from_dict
    from synth.generate import cfg_json, run_writer

    assert "distinct" not in cfg_json(GeneratorConfig())["people"]
    two = dataclasses.replace(TINY, people=PeopleConfig(min=1, max=2))
    writer = run_writer(two, tmp_path)
    before = json.loads(json.dumps(writer.manifest({})))  # as read back from a manifest of before
    before["config"]["people"].pop("distinct")
    with pytest.raises(ValueError, match="config differs from this run"):
        writer.same_run(before, tmp_path / "manifest.json")
    for people in (PeopleConfig(), PeopleConfig(distinct=True), PeopleConfig(max=2),
                   PeopleConfig(max=2, distinct=False)):  # fmt: skip
        cfg = dataclasses.replace(TINY, people=people)
        assert from_dict(GeneratorConfig, cfg_json(cfg)) == cfg
