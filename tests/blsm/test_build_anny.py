"""The model builder's geometry steps, on small synthetic meshes (Anny itself is exercised by
`make model`, which takes minutes)."""

from __future__ import annotations

import numpy as np
import pytest

from blsm import skeleton

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("pyfqmr")
pytest.importorskip("shapely")


def test_symmetric_half_decimation_gives_a_closed_symmetric_mesh():
    from blsm.build_anny import symmetric_half_decimation

    mesh = trimesh.creation.icosphere(subdivisions=4)
    v = mesh.vertices * np.array([0.3, 1.0, 0.5])
    v, f, mirror = symmetric_half_decimation(v, mesh.faces, half_faces=400)
    out = trimesh.Trimesh(v, f, process=False)
    assert out.is_watertight and out.is_winding_consistent and out.volume > 0
    assert len(f) < len(mesh.faces)
    assert np.allclose(v[mirror] * np.array([-1, 1, 1]), v, atol=1e-9)
    assert np.array_equal(mirror[mirror], np.arange(len(v)))


def test_barycentric_embedding_reproduces_points_on_the_surface():
    pytest.importorskip("rtree")
    from blsm.build_anny import barycentric_embedding, barycentric_interpolate

    mesh = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(0)
    w = rng.dirichlet(np.ones(3), size=50)
    pts = np.einsum("pk,pkc->pc", w, mesh.triangles[rng.integers(0, len(mesh.faces), 50)])
    tri, bary = barycentric_embedding(mesh.vertices, mesh.faces, pts)
    back = barycentric_interpolate(mesh.vertices, mesh.faces, tri, bary)
    assert np.allclose(back, pts, atol=1e-6)


def test_anny_bone_groups_cover_every_bone_once():
    from blsm.build_anny import anny_bone_groups

    labels = ["root", "pelvis.L", "pelvis.R", "spine05", "spine04", "spine03", "spine02", "spine01",
              "neck01", "neck02", "neck03", "head", "eye.L", "eye.R"]
    for s in ("L", "R"):
        labels += [f"{b}.{s}" for b in ("clavicle", "shoulder01", "upperarm01", "upperarm02",
                   "lowerarm01", "lowerarm02", "wrist", "finger1-1", "metacarpal1", "upperleg01",
                   "upperleg02", "lowerleg01", "lowerleg02", "foot", "toe1-1")]
    groups = anny_bone_groups(labels)
    assert len(groups) == len(skeleton.BONE_NAMES)
    assert labels[groups[skeleton.BONE_NAMES.index("wrist_r")][0]] == "wrist.R"
    assert "finger1-1.L" in [labels[i] for i in groups[skeleton.BONE_NAMES.index("wrist_l")]]
    with pytest.raises(RuntimeError, match="not mapped"):
        anny_bone_groups(labels + ["tail"])


def test_bind_frames_are_mirror_images_with_x_negated():
    heads = np.array([[0.2, 1.0, 0.0], [-0.2, 1.0, 0.0]])
    tails = np.array([[0.5, 0.8, 0.1], [-0.5, 0.8, 0.1]])
    for rule in ("lateral", "frontal"):
        f = skeleton.bind_frames(heads, tails, (rule, rule))
        reflect = np.diag([-1.0, 1.0, 1.0])
        assert np.allclose(reflect @ f[0], f[1] @ np.diag([-1.0, 1.0, 1.0]))
        assert np.allclose(np.linalg.det(f), 1.0)
