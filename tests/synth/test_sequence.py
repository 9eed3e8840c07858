"""Sequences (docs/video.md): the camera paths, placement, contact, and tiny sequence datasets end to
end (validation, labels, resume after SIGKILL mid-sequence, two workers), distinct people in a clip."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from tiny_run import drawing_maker, drawn

import blsm
from blsm.mocap.library import MotionClip, save_clip
from synth.camera import CameraConfig
from synth.camera_paths import PATHS, Track, sample_path
from synth.config import (
    BackgroundConfig,
    CameraPaths,
    GeneratorConfig,
    PeopleConfig,
    PosesConfig,
    RenderConfig,
    SequenceConfig,
    SubjectsConfig,
    load_config,
)
from synth.dataset import format as fmt
from synth.dataset.shards import read_shard
from synth.generate import generate
from synth.sequence import (
    CONTACT_REGIONS,
    RULE_POINT,
    TOE_BASE,
    clip_segments,
    contact,
    contact_regions,
    place_tracks,
    toe_base,
)
from synth.validate import validate

ROOT = Path(__file__).resolve().parents[2]


def _walk(
    name: str, frames: int = 45, fps: float = 30.0, speed: float = 1.2, cut: bool = False
) -> MotionClip:
    """A walk-like clip: the root moves along +Z at ``speed`` m/s, the atoms swing at 1 Hz."""
    model = blsm.load()
    t = np.arange(frames) / fps
    pose = 0.4 * np.sin(2 * math.pi * t[:, None] + np.arange(model.num_dofs)[None] * 0.7)
    transl = np.stack([0.05 * np.sin(2 * math.pi * t), 0.9 + 0.01 * np.sin(4 * math.pi * t), speed * t], 1)
    if cut:
        transl[0] = 0.0  # a calibration frame at the origin, as CMU files often start
    z = np.zeros(frames)
    return MotionClip(name=name, fps=fps, pose=pose.astype(np.float32), global_orient=np.zeros((frames, 3), np.float32),
                      transl=transl.astype(np.float32), dir_err_mean_deg=z, dir_err_max_deg=z, mpjpe_mm=z,
                      segment_err_deg=np.zeros((frames, 0)), meta={"dof_names": list(model.dof_names), "segments": []})  # fmt: skip


@pytest.fixture(scope="session")
def library(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("motions")
    save_clip(_walk("walk", cut=True), out / "walk.npz")
    save_clip(_walk("stroll", speed=0.6), out / "stroll.npz")
    return out


def _cfg(library: Path, **over) -> GeneratorConfig:
    cfg = GeneratorConfig(
        seed=3, num=2,
        subjects=SubjectsConfig(count=2, texture_size=128),
        poses=PosesConfig(source="library", library=str(library)),
        people=PeopleConfig(min=1, max=2),
        camera=CameraConfig(width=64, height=64),
        background=BackgroundConfig(env_width=128),
        render=RenderConfig(spp=4),
        sequence=SequenceConfig(enabled=True, frames=4, fps=30.0, cameras=CameraPaths(orbit=4.0, zoom=4.0)),
    )  # fmt: skip
    return dataclasses.replace(cfg, **over)


@pytest.fixture(scope="session")
def clips(library, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("clips")
    generate(_cfg(library), out, progress=False)
    return out


def _docs(dataset: Path) -> list[dict]:
    from synth.dataset.index import DatasetIndex

    index = DatasetIndex(dataset)
    try:
        return [index.json(i) for i in range(len(index))]
    finally:
        index.close()


def test_a_sequence_dataset_validates_and_carries_the_sequence_labels(clips):
    rep = validate(clips)
    assert rep.failures == [] and rep.samples == 8
    man = json.loads((clips / "manifest.json").read_text())
    assert man["num_samples"] == 8 and man["shard_size"] == 4 and len(man["shards"]) == 2
    docs = _docs(clips)
    assert [(d["sequence"], d["frame"]) for d in docs] == [(s, f) for s in range(2) for f in range(4)]
    for s in range(2):
        clip = docs[4 * s : 4 * s + 4]
        kinds = {d["camera"]["path"]["kind"] for d in clip}
        assert len(kinds) == 1 and kinds <= set(PATHS)
        subjects = {tuple(p["subject"] for p in d["people"]) for d in clip}
        assert len(subjects) == 1  # the same people throughout
        assert len({json.dumps(d["background"]["rotation"]) for d in clip}) == 1
    for d in docs:
        assert d["time"] == pytest.approx(d["frame"] / 30.0)
        assert 1 <= d["camera"]["path"]["tries"] <= 21
        eye = -np.array(d["camera"]["R"]).T @ np.array(d["camera"]["t"])
        near = min(np.linalg.norm(np.array(p["keypoints_3d"]) - eye, axis=1).min() for p in d["people"])
        assert near > 0.3 or d["camera"]["path"]["tries"] == 21  # the camera keeps clear of the bodies
        r, t = np.array(d["camera"]["R"]), np.array(d["camera"]["t"])
        c = np.array(d["camera"]["to_world"])
        assert np.allclose(c[:3, :3], r.T, atol=2e-6) and np.allclose(c[:3, 3], -r.T @ t, atol=2e-5)
        for i, p in enumerate(d["people"]):
            assert p["track"] == i and set(p["contact"]) == set(CONTACT_REGIONS) == set(p["contact_velocity"])
            x = np.array(p["keypoints_3d"])
            assert np.allclose(
                x @ r.T + t, np.array(p["keypoints_3d_cam"]), atol=1e-5
            )  # R X_world + t = X_cam
            assert np.array(p["velocity_3d"]).shape == x.shape
            assert p["in_view"] == (p["pixels"] > 0)


def test_the_people_walk_the_clips_path_in_the_world_frame(clips):
    """Root speed follows the clip (1.2 or 0.6 m/s scaled by the legs), the lowest vertex sits on the
    ground, and the keypoints' velocity is the root's where the body moves rigidly (the pelvis)."""
    docs = _docs(clips)
    pelvis = docs[0]["keypoint_names"].index("pelvis")
    for s in range(2):
        clip = docs[4 * s : 4 * s + 4]
        for i in range(len(clip[0]["people"])):
            root = np.array([d["people"][i]["blsm"]["transl"] for d in clip])
            speed = np.linalg.norm(np.diff(root[:, [0, 2]], axis=0), axis=1) * 30
            scale = clip[0]["people"][i]["clip_window"]["leg_scale"]
            nominal = {"walk": 1.2, "stroll": 0.6}[clip[0]["people"][i]["motion"]["clip"]] * scale
            assert np.allclose(speed, nominal, rtol=0.15)
            v = np.array([d["people"][i]["velocity_3d"][pelvis] for d in clip])
            assert np.allclose(np.linalg.norm(v[:, [0, 2]], axis=1), nominal, rtol=0.15)


def test_validate_catches_a_sequence_whose_frames_jump_or_touch_nothing(clips, tmp_path):
    from synth.validate_sequence import check_contact, check_sequences

    docs = _docs(clips)
    clip = {f"{i:09d}": d for i, d in enumerate(docs[:4])}
    cfg = {"frames": 4, "fps": 30.0}
    assert check_sequences(clip, cfg, 0) == []
    bad = json.loads(json.dumps(clip))
    bad["000000002"]["people"][0]["blsm"]["transl"][0] += 1.0
    assert any("jumps" in m for m in check_sequences(bad, cfg, 0))
    bad = json.loads(json.dumps(clip))
    bad["000000001"]["frame"] = 3
    assert any("frame 1 is labelled" in m for m in check_sequences(bad, cfg, 0))
    bad = json.loads(json.dumps(clip))
    for d in bad.values():
        d["people"][0]["velocity_3d"] = (np.array(d["people"][0]["velocity_3d"]) / 30).tolist()  # m/frame
    assert any("velocity_3d differs" in m for m in check_sequences(bad, cfg, 0))
    # Contact said where the body is 0.5 m up.
    from synth.validate import MeshRebuilder

    d = docs[0]
    p = dict(d["people"][0], contact={r: True for r in CONTACT_REGIONS})
    rb = MeshRebuilder(clips, {})
    v, _, kp = rb.mesh(p)
    msgs = check_contact(rb.model, rb.bones, v[: len(rb.bones)], kp, p, d)
    assert any(m.startswith("contact head") for m in msgs) is False
    assert any("above the ground" in m for m in msgs)
    # The whole rule (nearness and speed) at the inner frames, on the rebuilt bodies.
    regions: dict = {}
    for q in clip.values():
        for person in q["people"]:
            v, _, kp = rb.mesh(person)
            check_contact(rb.model, rb.bones, v[: len(rb.bones)], kp, person, q, regions)
    assert check_sequences(clip, cfg, 0) == []
    q = clip["000000001"]["people"][0]
    stance = next((r for r in CONTACT_REGIONS if q["contact"][r]), None)
    flip = stance or "heel_l"
    q["contact"][flip] = not q["contact"][flip]
    assert any(f"frame 1 contact {flip}" in m for m in check_sequences(clip, cfg, 0))


def test_sigkill_mid_sequence_then_resume_gives_the_same_bytes(library, clips, tmp_path):
    """Killed while a sequence is being made (after the first sequence's shard) and resumed: the
    same shards, byte for byte, as the uninterrupted run."""
    import shutil

    yaml = f"""seed: 3
num: 2
subjects: {{count: 2, texture_size: 128}}
poses: {{source: library, library: {library}}}
people: {{min: 1, max: 2}}
camera: {{width: 64, height: 64}}
background: {{env_width: 128}}
render: {{spp: 4}}
sequence: {{enabled: true, frames: 4, fps: 30.0, cameras: {{orbit: 4.0, zoom: 4.0}}}}
"""
    assert load_config_text(yaml, tmp_path) == _cfg(library)
    out = tmp_path / "killed"
    out.mkdir()
    shutil.copytree(clips / "subjects", out / "subjects")
    cmd = [sys.executable, "-m", "synth.cli", "generate", str(tmp_path / "seq.yaml"), "--out", str(out)]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while not (out / "manifest.json").exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.01)
    assert proc.poll() is None, "the run ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not json.loads((out / "manifest.json").read_text())["complete"]
    r = subprocess.run(cmd + ["--resume"], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    for name in ("shard-000000.tar", "shard-000001.tar"):
        assert (out / name).read_bytes() == (clips / name).read_bytes()


def load_config_text(text: str, tmp_path: Path) -> GeneratorConfig:
    (tmp_path / "seq.yaml").write_text(text)
    return load_config(tmp_path / "seq.yaml")


def test_two_workers_make_the_same_sequences_as_one(library, clips, tmp_path):
    import shutil

    out = tmp_path / "two"
    out.mkdir()
    shutil.copytree(clips / "subjects", out / "subjects")
    generate(_cfg(library), out, workers=2, progress=False)
    for name in ("shard-000000.tar", "shard-000001.tar"):
        assert (out / name).read_bytes() == (clips / name).read_bytes()


def test_single_image_manifests_hold_no_sequence_section():
    from synth.generate import cfg_json

    assert "sequence" not in cfg_json(GeneratorConfig())
    assert cfg_json(_cfg(Path("x")))["sequence"]["frames"] == 4


@pytest.mark.parametrize("kind", PATHS)
def test_every_camera_path_is_exact_smooth_and_does_what_it_says(kind):
    rng = np.random.default_rng(5)
    times = np.arange(60) / 30.0
    centre = np.stack([np.zeros(60), np.full(60, 0.9), 1.2 * times], 1)  # a person walking along +Z
    body = np.array([[x, y, z] for x in (-0.3, 0.3) for y in (0.0, 1.8) for z in (-0.15, 0.15)])
    everyone = np.concatenate([body + c for c in centre[::6]])
    path = sample_path(
        kind,
        CameraConfig(width=128, height=128),
        CameraPaths(),
        everyone,
        body + centre[0],
        Track(times, centre),
        times[-1],
        rng,
    )
    cams = [path.at(t) for t in times]
    eyes = np.array([-c.R.T @ c.t for c in cams])
    for c in cams:
        assert np.allclose(c.R @ c.R.T, np.eye(3), atol=1e-9) and np.linalg.det(c.R) > 0
    steps = np.linalg.norm(np.diff(eyes, axis=0), axis=1) * 30
    assert steps.max() < 5.0  # no jump
    focal = np.array([c.K[0, 0] for c in cams])
    assert path.info["kind"] == kind
    if kind in ("static", "portrait", "long_lens", "zoom"):
        assert np.allclose(eyes, eyes[0]) and (kind == "zoom" or np.allclose([c.R for c in cams], cams[0].R))
    if kind == "zoom":
        ratio = focal[-1] / focal[0]
        r = path.info["ratio"]
        assert ratio == pytest.approx(r if path.info["direction"] == "in" else 1 / r)
    else:
        assert np.allclose(focal, focal[0])
    if kind == "portrait":
        roll = math.degrees(math.atan2(cams[0].R[0, 1], cams[0].R[1, 1]))
        assert abs(abs(roll) - 90.0) < 15.0
    if kind == "long_lens":
        mm = focal[0] * 36.0 / 128
        assert 135.0 <= mm <= 300.0
    if kind == "dolly":
        assert np.linalg.norm(eyes[-1] - eyes[0]) == pytest.approx(abs(path.info["distance_m"]), rel=1e-6)
        assert np.allclose([c.R for c in cams], cams[0].R)
    if kind == "orbit":
        c0 = np.array(path.info["centre"])
        a = [math.atan2(*(e - c0)[[0, 2]]) for e in eyes]
        speed = np.degrees(np.diff(np.unwrap(a))) * 30
        assert np.allclose(speed, path.info["deg_s"], rtol=1e-6)
    if kind == "pan":  # the followed centre stays near the image centre
        uv = np.array(
            [c.project(p[None])[0] for c, p in zip(cams, Track(times, centre).smoothed(0.4).points, strict=False)]
        )
        assert np.abs(uv - 64).max() < 1.0
    if kind == "tracking":  # a steady walk: the camera keeps its offset exactly
        off = eyes - centre
        assert np.abs(off - off[0])[:, [0, 2]].max() < 1e-6 and np.allclose(eyes[:, 1], eyes[0, 1])
    if kind == "handheld":
        turn = [math.degrees(math.acos(np.clip((np.trace(c.R @ cams[0].R.T) - 1) / 2, -1, 1))) for c in cams]
        assert 0.0 < max(turn) < 3 * (1.5 + 0.15) * 2
        assert np.abs(eyes - eyes[0]).max() < 2 * 0.02 * 2


def test_trajectories_are_placed_apart_at_every_frame():
    rng = np.random.default_rng(0)
    t = np.arange(50) / 30.0
    fps = [np.stack([np.zeros(50), 1.5 * t, np.full(50, 0.4)], 1),  # walking along z
           np.stack([1.5 * t - 1.0, np.zeros(50), np.full(50, 0.4)], 1),  # across it
           np.stack([np.zeros(50), np.zeros(50), np.full(50, 0.3)], 1)]  # fmt: skip
    offs = place_tracks(fps, 0.1, rng)
    for i in range(3):
        for j in range(i):
            d = np.linalg.norm(fps[i][:, :2] + offs[i] - fps[j][:, :2] - offs[j], axis=1)
            assert (d >= fps[i][:, 2] + fps[j][:, 2] + 0.1 - 1e-9).all()


def test_contact_needs_both_nearness_and_stillness_and_regions_split_the_foot():
    assert contact(np.array([0.01, 0.2]), np.array([0.1, 0.0]), 0.03, 0.3)
    assert not contact(np.array([0.01, 0.2]), np.array([0.5, 0.0]), 0.03, 0.3)  # near but sliding
    assert not contact(np.array([0.05]), np.array([0.0]), 0.03, 0.3)  # still but above
    model = blsm.load()
    out = model()
    v = out.vertices[0].numpy()
    kp = out.keypoints[0].numpy()
    reg = contact_regions(model, model.vertex_bones.numpy(), v, kp)
    foot = np.nonzero(model.vertex_bones.numpy() == list(model.bone_names).index("ankle_l"))[0]
    assert sorted(np.concatenate([reg["heel_l"], reg["toe_l"]])) == sorted(foot)
    assert v[reg["heel_l"], 2].mean() < v[reg["toe_l"], 2].mean()  # the heel behind the toes (+Z forward)
    assert all(len(reg[r]) for r in CONTACT_REGIONS)
    names = list(model.keypoint_names)
    for s in ("l", "r"):  # the toe base: inside the forefoot, at the metatarsal heads
        idx = toe_base(model, model.vertex_bones.numpy(), v, kp)[f"toe_{s}"]
        assert len(idx) >= 8 and set(idx) <= set(reg[f"toe_{s}"])
        heel, tip, ankle = (kp[names.index(f"{k}_{s}")] for k in ("heel", "toe_tip", "ankle"))
        c = v[idx].mean(0)
        u = (c - heel) @ (tip - heel) / ((tip - heel) @ (tip - heel))
        assert TOE_BASE[0] - 0.02 < u < TOE_BASE[1] + 0.02
        assert v[idx, 1].min() < c[1] < min(ankle[1], v[idx, 1].max())  # between sole and instep, below the ankle


def test_contact_velocity_follows_the_heel_and_the_toe_base(library, tmp_path):
    """The velocity rule of the labels, recomputed on the rebuilt bodies of the frames with both
    neighbours: the heel keypoint for the heels, the toe base's centroid for the toes. The fake clips
    swing every atom, so the feet move at 2-5 m/s; a threshold of 3 m/s puts some toe tips and toe
    bases on its two sides, so a rule on the toe tip fails the test."""
    from synth.config import ContactConfig
    from synth.validate import MeshRebuilder

    T = 6
    seq = SequenceConfig(enabled=True, frames=T, fps=30.0, cameras=CameraPaths(static=1.0),
                         contact=ContactConfig(velocity_rule=3.0))  # fmt: skip
    cfg = _cfg(library, sequence=seq, people=PeopleConfig(min=2, max=2), render=RenderConfig(spp=1))
    generate(cfg, tmp_path, progress=False)
    rebuild = MeshRebuilder(tmp_path, json.loads((tmp_path / "manifest.json").read_text())["config"])
    docs = _docs(tmp_path)
    names = docs[0]["keypoint_names"]
    checked = straddle = 0
    for a in range(0, len(docs), T):
        clip = docs[a : a + T]
        for i in range(len(clip[0]["people"])):
            pts = []
            for f, d in enumerate(clip):
                assert d["contact_rule"]["velocity_points"] == RULE_POINT
                v, _, kp = rebuild.mesh(d["people"][i])
                if f == 0:
                    base = toe_base(rebuild.model, rebuild.bones, v, kp)
                pts.append([kp[names.index(n)] for n in ("heel_l", "heel_r", "toe_tip_l", "toe_tip_r")]
                           + [v[base["toe_l"]].mean(0), v[base["toe_r"]].mean(0)])  # fmt: skip
            pts = np.array(pts)
            for f in range(1, T - 1):
                speed = np.linalg.norm(pts[f + 1] - pts[f - 1], axis=1) * 30.0 / 2
                heel_l, heel_r, tip_l, tip_r, base_l, base_r = speed
                for r, sp, tip in (("heel_l", heel_l, None), ("heel_r", heel_r, None), ("toe_l", base_l, tip_l),
                                   ("toe_r", base_r, tip_r)):  # fmt: skip
                    if abs(sp - 3.0) > 1e-3:  # the labels' 6-decimal rounding decides nothing
                        assert clip[f]["people"][i]["contact_velocity"][r] == bool(sp <= 3.0), (a, i, f, r, sp)
                        checked += 1
                        straddle += tip is not None and (tip <= 3.0) != (sp <= 3.0)
    assert checked >= 40 and straddle >= 1


def test_clip_segments_split_at_a_cut_of_the_root_or_a_joint():
    clip = _walk("w", cut=True)
    limits = blsm.load().dof_limits.numpy()
    assert clip_segments(clip) == [(1, 44)] == clip_segments(clip, limits)
    wide = int(np.argmax(limits[:, 1] - limits[:, 0]))
    clip.pose[20:, wide] = 9.0  # the widest atom jumps from mid-range to its limit in one frame
    assert clip_segments(clip, limits) == [(1, 19), (20, 44)]


def test_bad_sequence_configs_are_one_line_errors(library, tmp_path):
    with pytest.raises(ValueError, match="needs poses.source: library"):
        GeneratorConfig(sequence=SequenceConfig(enabled=True))
    with pytest.raises(ValueError, match="backplate photograph cannot follow a moving camera"):
        _cfg(library, background=BackgroundConfig(kind="images", folder="x"))
    with pytest.raises(ValueError, match="subframes must be odd"):
        SequenceConfig(motion_blur=dataclasses.replace(SequenceConfig().motion_blur, subframes=4))
    from synth.generate import check_inputs

    long = _cfg(library, sequence=dataclasses.replace(_cfg(library).sequence, frames=60))
    with pytest.raises(ValueError, match=r"no clip holds 2\.0\d s without a cut"):
        check_inputs(long, blsm.load())


def test_motion_blur_averages_subframes_and_keeps_the_centre_labels(library, clips, tmp_path):
    """With motion blur the labels are the unblurred run's (the centre sub-frame is the frame's own
    time) and the image differs where people move."""
    import shutil

    from synth.config import MotionBlur

    out = tmp_path / "blur"
    out.mkdir()
    shutil.copytree(clips / "subjects", out / "subjects")
    seq = dataclasses.replace(
        _cfg(library).sequence, motion_blur=MotionBlur(enabled=True, subframes=3, shutter=0.5)
    )
    generate(dataclasses.replace(_cfg(library, num=1), sequence=seq), out, progress=False)
    assert validate(out).failures == []
    a, b = read_shard(out / "shard-000000.tar"), read_shard(clips / "shard-000000.tar")
    for k in a:
        ja, jb = json.loads(a[k]["json"]), json.loads(b[k]["json"])
        assert ja["motion_blur"] == {"subframes": 3, "shutter": 0.5}
        assert [p["keypoints_2d"] for p in ja["people"]] == [p["keypoints_2d"] for p in jb["people"]]
        assert a[k]["mask.png"] == b[k]["mask.png"]
    rgb_a = fmt.decode_sample(a["000000001"])["rgb"].astype(float)
    rgb_b = fmt.decode_sample(b["000000001"])["rgb"].astype(float)
    assert np.abs(rgb_a - rgb_b).mean() > 0.1


def test_a_warm_worker_compiles_no_kernel_for_new_sequences(library, clips):
    """After its first sequence, a worker making new sequences (other people, clips, camera paths,
    zoom changing the focal length within a shot) launches only kernels it has compiled already."""
    import drjit as dr

    from blsm.mitsuba_util import resolve_variant
    from synth.sample import SampleMaker
    from synth.sequence import SequenceMaker, sequence_rng

    cfg = _cfg(library, sequence=dataclasses.replace(_cfg(library).sequence, cameras=CameraPaths()))
    maker = SampleMaker(cfg, clips, resolve_variant(None), threads=0)
    seqs = SequenceMaker(maker)
    seqs.make(100, sequence_rng(cfg.seed, 100))  # warm-up
    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        kinds = set()
        for s in range(200, 206):
            kinds.add(json.loads(seqs.make(s, sequence_rng(cfg.seed, s))[0]["json"])["camera"]["path"]["kind"])
        history = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, was)
    assert len(kinds) >= 3
    jit = [k for k in history if k["type"] == dr.KernelType.JIT]
    assert len(jit) >= 6 * 4 * 3
    new = [(k["hash"], k["size"]) for k in jit if not k["cache_hit"] or k["cache_disk"]]
    assert new == [], f"{len(new)} kernels compiled or loaded for new sequences"


def test_a_person_wholly_behind_the_camera_has_no_box_and_loads():
    """A moving camera can pass a person by: every label of that person says so (no pixel, no box,
    ``box_full`` null, nothing in frame), and the clip loader fills the crop from the other frames."""
    from blsm.camera import look_at_camera
    from synth import labels as lab
    from synth.dataset.sequences import fill_missing_boxes
    from synth.render import Frame

    model = blsm.load()
    out = model()
    v, kp = out.vertices[0].numpy().astype(np.float64), out.keypoints[0].numpy().astype(np.float64)
    cam = look_at_camera(np.array([0.0, 1.0, -3.0]), np.array([0.0, 1.0, -10.0]), width=32, height=32)  # facing away
    frame = Frame(rgb=np.zeros((32, 32, 3), np.float32), alpha=np.zeros((32, 32), np.float32), hit=np.zeros((32, 32), bool),
                  position=np.zeros((32, 32, 3), np.float32), face=np.full((32, 32), -1))  # fmt: skip
    faces = model.faces.numpy()
    m = model
    res = lab.person_labels(
        frame, cam, [{"vertices": v, "faces": faces, "face_bones": lab.face_bones(faces, m.weights.numpy()), "keypoints": kp}],
        lab.bone_parts(m.vertex_bones.numpy(), m.vertex_parts.numpy(), m.num_joints),
        lab.keypoint_regions(m.keypoint_joint.numpy(), m.keypoint_vertices.numpy(), m.vertex_bones.numpy(), m.parents),
        m.keypoint_joint.numpy() >= 0,
    )  # fmt: skip
    p = res["people"][0]
    assert p["box"] is None and p["box_full"] is None and p["pixels"] == 0 and not p["in_frame"].any()
    boxes = np.array([[0, 0, 10, 10], [np.nan] * 4, [np.nan] * 4, [6, 0, 16, 10]], np.float64)
    assert np.allclose(fill_missing_boxes(boxes), [[0, 0, 10, 10], [2, 0, 12, 10], [4, 0, 14, 10], [6, 0, 16, 10]])


def test_the_people_of_one_sequence_are_distinct_subjects(library, tiny):
    """Issue 53: with a pool of 8 subjects the people of a clip are as many subjects, a sequence's
    draw is still its ``(seed, sequence)``'s; with 2 subjects for 3 people, both are in every clip."""
    from synth.sequence import SequenceMaker, sequence_rng

    cfg = _cfg(library, people=PeopleConfig(min=2, max=3))
    seqs = SequenceMaker(drawing_maker(cfg, tiny, pool=8))
    draws = [drawn(seqs.make, s, sequence_rng(cfg.seed, s)) for s in range(16)]
    twins = {s: d for s, d in enumerate(draws) if len(set(d)) < len(d)}
    assert twins == {}, f"the same subject twice in one sequence: {twins}"
    assert {len(d) for d in draws} == {2, 3}
    again = SequenceMaker(drawing_maker(cfg, tiny, pool=8))
    assert [drawn(again.make, s, sequence_rng(cfg.seed, s)) for s in (12, 3)] == [draws[12], draws[3]]
    few = dataclasses.replace(cfg, people=PeopleConfig(min=3, max=3))
    seqs = SequenceMaker(drawing_maker(few, tiny, pool=2))
    draws = [drawn(seqs.make, s, sequence_rng(cfg.seed, s)) for s in range(4)]
    assert all(len(d) == 3 and sorted(set(d)) == [0, 1] for d in draws), draws
