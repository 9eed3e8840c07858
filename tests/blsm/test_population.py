from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from blsm.learn.scans import population as P
from blsm.learn.scans.format import landmark_points, load_scan

pytest.importorskip("anny")


@pytest.fixture(scope="module")
def rig(model):
    return P.anny_rig(model)


@pytest.fixture(scope="module")
def bodies(model):
    subs = [P.sample_subject(i, seed=3) for i in range(2)]
    return P.rest_bodies(model, [s["phenotype"] for s in subs], [s["local_changes"] for s in subs])


@pytest.fixture(scope="module")
def population(tmp_path_factory, model):
    out = tmp_path_factory.mktemp("pop")
    index = P.make_population(
        out, 3, posed_subjects=1, poses_per_subject=1, seed=5, test_fraction=0.5, model=model
    )
    return out, index


def test_zero_pose_is_rest(model, rig, bodies):
    posed = P.pose_anny(model, rig, bodies, torch.zeros(2, model.num_dofs, dtype=torch.float64))
    np.testing.assert_allclose(posed, bodies.vertices, atol=1e-9)
    # Root joint on the BLSM root joint.
    np.testing.assert_allclose(bodies.heads[:, 0], model.heads[0].numpy()[None].repeat(2, 0), atol=1e-9)


def test_elbow_flexion_moves_only_forearm(model, rig, bodies):
    ang = torch.zeros(2, model.num_dofs, dtype=torch.float64)
    ang[:, model.dof_names.index("elbow_l.flex")] = 1.0
    moved = np.linalg.norm(P.pose_anny(model, rig, bodies, ang) - bodies.vertices, axis=-1)  # (2, Va)
    fore = [model.bone_names.index(n) for n in ("elbow_l", "wrist_l")]
    w_fore = rig.weights[:, np.isin(rig.blsm_bone, fore)].sum(1)
    assert moved[:, w_fore == 0].max() < 1e-9  # nothing outside the forearm's influence moves
    assert moved[:, w_fore > 0.99].min() > 0.001  # the forearm and hand do (least at the elbow)
    assert np.median(moved[:, w_fore > 0.99]) > 0.1


def test_translation_and_orient(model, rig, bodies):
    ang = torch.zeros(2, model.num_dofs, dtype=torch.float64)
    orient = torch.tensor([[0.0, np.pi, 0.0]] * 2, dtype=torch.float64)
    transl = torch.tensor([[0.1, 0.2, 0.3]] * 2, dtype=torch.float64)
    posed = P.pose_anny(model, rig, bodies, ang, orient, transl)
    root = model.heads[0].numpy()
    expect = (bodies.vertices - root) * [-1, 1, -1] + root + [0.1, 0.2, 0.3]
    np.testing.assert_allclose(posed, expect, atol=1e-6)
    with pytest.raises(ValueError, match="angles must be"):
        P.pose_anny(model, rig, bodies, torch.zeros(1, model.num_dofs))


def test_subjects_reproducible():
    a, b = P.sample_subject(4, seed=1), P.sample_subject(4, seed=1)
    assert a == b
    assert P.sample_subject(5, seed=1)["phenotype"] != a["phenotype"]
    assert P.sample_subject(4, seed=2)["phenotype"] != a["phenotype"]
    assert all(-0.3 <= v <= 0.3 for v in a["local_changes"].values()) and a["local_changes"]


def test_population_folder(population, model):
    out, index = population
    back = json.loads((out / "index.json").read_text())
    assert back["format"] == "blsm-population" and back["version"] == 1 and back["seed"] == 5
    assert [len(s["scans"]) for s in back["subjects"]] == [2, 1, 1]
    assert {s["split"] for s in back["subjects"]} <= {"train", "test"}
    assert P.read_population(out)["subjects"] == back["subjects"]
    with pytest.raises(ValueError, match="already exists"):
        P.make_population(out, 1, model=model)
    rest = load_scan(out / back["subjects"][0]["scans"][0], require_landmarks=True)
    posed = load_scan(out / back["subjects"][0]["scans"][1])
    assert np.abs(rest.gt_angles).max() == 0 and np.abs(posed.gt_angles).max() > 0.05
    assert rest.gt_points.shape == (model.num_vertices, 3)
    assert rest.meta["subject"] == posed.meta["subject"] == "s00000"
    # Artefacts: holes remove vertices, so the scan topology is not Anny's.
    assert rest.meta["artefacts"]["removed_vertices"] > 100
    assert len(rest.vertices) < 13348 - 100


def test_gt_points_on_surfaces(population, model, rig):
    import trimesh

    out, index = population
    scan = load_scan(out / index["subjects"][0]["scans"][1])
    gt = scan.gt_points.astype(np.float64)
    # The clean posed body, rebuilt: the gt points lie on it (distance ~ 0).
    sub = P.sample_subject(0, seed=5)
    bodies = P.rest_bodies(model, [sub["phenotype"]], [sub["local_changes"]])
    clean = P.pose_anny(
        model,
        rig,
        bodies,
        torch.as_tensor(scan.gt_angles, dtype=torch.float64)[None],
        torch.as_tensor(scan.gt_global_orient, dtype=torch.float64)[None],
    )[0]
    sample = gt[::10]
    _, d_clean, _ = trimesh.proximity.closest_point(trimesh.Trimesh(clean, rig.faces, process=False), sample)
    assert d_clean.max() < 1e-5
    # Near the noisy scan surface: about the noise (1 mm), except at the holes.
    _, d_scan, _ = trimesh.proximity.closest_point(
        trimesh.Trimesh(scan.vertices, scan.faces, process=False), sample
    )
    assert np.median(d_scan) < 0.0015 and np.median(d_scan) > 1e-5
    # Located landmarks: gt landmark points plus ~5 mm noise.
    lm_gt = landmark_points(torch.as_tensor(gt)).numpy()
    ok = scan.located
    err = np.linalg.norm(scan.landmarks[ok] - lm_gt[ok], axis=1)
    assert 0.002 < np.median(err) < 0.02


def test_no_artefacts_and_bad_args(tmp_path, model):
    with pytest.raises(ValueError, match="n_subjects"):
        P.make_population(tmp_path / "p", 0, model=model)
    with pytest.raises(ValueError, match="test_fraction"):
        P.make_population(tmp_path / "p", 1, test_fraction=2.0, model=model)
    with pytest.raises(ValueError, match="must be >= 0"):
        P.Artefacts(noise=-1.0)
    index = P.make_population(tmp_path / "clean", 1, artefacts=P.NO_ARTEFACTS, model=model)
    scan = load_scan(tmp_path / "clean" / index["subjects"][0]["scans"][0])
    assert len(scan.vertices) == 13348 and scan.located.all()
    np.testing.assert_allclose(
        landmark_points(torch.as_tensor(scan.gt_points)).numpy(), scan.landmarks, atol=1e-6
    )


def test_main_cli(tmp_path):
    from blsm.cli import main

    assert main(["scans", "make", "--out", str(tmp_path / "c"), "--subjects", "1", "--seed", "2"]) == 0
    assert (tmp_path / "c" / "scans" / "s00000_00.npz").is_file()
    with pytest.raises(SystemExit):
        main(["scans", "make", "--subjects", "1"])


def test_poses_from_motion_library(tmp_path, model):
    from blsm.joint_limits import angles_from_unconstrained
    from blsm.mocap.library import MotionClip, save_clip

    t = 3
    x = np.zeros((t, model.num_dofs), np.float32)
    x[:, model.dof_names.index("knee_l.flex")] = 2.0  # unconstrained: a clearly bent knee
    z3, z1 = np.zeros((t, 3), np.float32), np.zeros(t, np.float32)
    clip = MotionClip(
        "bend", 30.0, x, z3, z3, z1, z1, z1, np.zeros((t, 0), np.float32),
        meta={"dof_names": list(model.dof_names), "segments": []},
    )  # fmt: skip
    save_clip(clip, tmp_path / "lib" / "bend.npz")
    index = P.make_population(
        tmp_path / "p", 1, posed_subjects=1, poses_per_subject=1, motions=tmp_path / "lib", model=model
    )
    scan = load_scan(tmp_path / "p" / index["subjects"][0]["scans"][1])
    assert scan.meta["pose_source"].startswith("bend:")
    expect = angles_from_unconstrained(torch.as_tensor(x[:1]), model.dof_limits)[0].numpy()
    np.testing.assert_allclose(scan.gt_angles, expect, atol=1e-6)
    assert abs(scan.gt_angles[model.dof_names.index("knee_l.flex")]) > 0.3
    with pytest.raises(ValueError, match="not a folder"):
        P.make_population(tmp_path / "q", 1, 1, 1, motions=tmp_path / "nothing", model=model)
