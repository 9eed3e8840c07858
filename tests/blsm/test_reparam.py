"""Reparameterisation (thesis ch. 3): correspondences, W, Eq. 3.5 in low rank, the model file, the
posed check and ``blsm reparam``'s bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

import blsm
from blsm import io
from blsm.cli import main
from blsm.learn.reparam.evaluate import compactness, generalisation, posed_check, specificity
from blsm.learn.reparam.mapping import (
    block_matrix,
    closest_point_triangle,
    closest_points,
    mapping_matrix,
    shape_space_eq35,
)
from blsm.learn.reparam.model import read_correspondence, reparameterise, subdivide_template
from blsm.model import DEFAULT_MODEL


@pytest.fixture(scope="module")
def packaged():
    return io.read_model(DEFAULT_MODEL)


@pytest.fixture(scope="module")
def midpoint(packaged, tmp_path_factory):
    """The packaged model reparameterised to its midpoint-subdivided template (28002 vertices)."""
    v, f = subdivide_template(packaged.arrays["template"], packaged.arrays["faces"], 1, "midpoint")
    data, report = reparameterise(packaged, v, f)
    path = tmp_path_factory.mktemp("reparam") / "mid1.npz"
    io.save_model(data, path)
    return path, report


def test_closest_point_triangle_against_dense_sampling():
    rng = np.random.default_rng(0)
    a, b, c = (rng.normal(size=(200, 3)) for _ in range(3))
    p = rng.normal(size=(200, 3)) * 2
    bary = closest_point_triangle(p, a, b, c)
    assert np.allclose(bary.sum(1), 1) and (bary >= 0).all()
    got = np.linalg.norm(p - (bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c), axis=1)
    u, v = np.meshgrid(np.linspace(0, 1, 120), np.linspace(0, 1, 120))
    u, v = u[u + v <= 1], v[u + v <= 1]
    for i in range(0, 200, 20):  # the exact distance is never beaten by a dense sample of the triangle
        pts = (1 - u - v)[:, None] * a[i] + u[:, None] * b[i] + v[:, None] * c[i]
        dense = np.linalg.norm(pts - p[i], axis=1).min()
        assert got[i] <= dense + 1e-12 and dense - got[i] < 0.02


def test_closest_points_match_trimesh_and_w_rows_sum_to_one():
    mesh = trimesh.creation.icosphere(2)
    p = np.random.default_rng(1).normal(size=(500, 3)) * 0.9
    corr = closest_points(p, mesh.vertices, mesh.faces)
    q, d, _ = trimesh.proximity.closest_point(mesh, p)
    assert np.allclose(corr.distance, d, atol=1e-12) and np.allclose(corr.points(mesh.vertices), q, atol=1e-12)
    wp = mapping_matrix(corr, len(mesh.vertices))
    assert np.allclose(np.asarray(wp.sum(1)).ravel(), 1.0)
    w = block_matrix(corr, len(mesh.vertices))  # Sec. 3.3.2's 3N2 x 3N1 W
    assert w.shape == (1500, 3 * len(mesh.vertices))
    assert np.allclose(w @ mesh.vertices.reshape(-1), q.reshape(-1), atol=1e-12)


def test_eq35_low_rank_equals_the_dense_covariance():
    mesh = trimesh.creation.icosphere(1)  # 42 vertices
    v2, f2 = subdivide_template(mesh.vertices, mesh.faces, 1, "loop")  # 162, shrunk: mu2 != W mu1
    rng = np.random.default_rng(2)
    basis = rng.normal(size=(4, 42, 3)) * 0.01
    wp = mapping_matrix(closest_points(v2, mesh.vertices, mesh.faces), 42)
    space = shape_space_eq35(wp, mesh.vertices, basis, v2)
    w = block_matrix(closest_points(v2, mesh.vertices, mesh.faces), 42).toarray()
    sigma1 = basis.reshape(4, -1).T @ basis.reshape(4, -1)
    d = v2.reshape(-1) - w @ mesh.vertices.reshape(-1)
    dense = w @ sigma1 @ w.T + np.outer(d, d)  # Eq. 3.5
    comps = space.components.reshape(len(space.variances), -1)
    assert len(space.variances) == 5 and np.allclose(comps.T @ comps, dense, atol=1e-12)
    assert np.allclose(np.sort(np.linalg.eigvalsh(dense))[::-1][:5], space.variances, atol=1e-12)
    # the coefficient map gives W times the source body exactly
    c = rng.normal(size=4)
    body = space.mean.reshape(-1) + (space.coeff_map @ c + space.coeff_offset) @ comps
    assert np.allclose(body, w @ (mesh.vertices.reshape(-1) + c @ basis.reshape(4, -1)), atol=1e-12)


def test_identity_template_gives_w_identity_and_the_same_model(packaged):
    a = packaged.arrays
    data, report = reparameterise(packaged, a["template"], a["faces"])
    b = data.arrays
    assert report["alignment"]["mode"] == "none" and report["coverage"]["new_to_old_mm"]["max"] < 1e-6
    w = mapping_matrix(closest_points(a["template"], a["template"], a["faces"]), len(a["template"]))
    assert np.allclose(w.toarray(), np.eye(len(a["template"])), atol=1e-6)
    for k in ("weights", "bone_correctives", "shape_basis", "template"):
        assert np.allclose(b[k], a[k], atol=1e-6), k
    for k in ("vertex_parts", "vertex_mirror", "faces"):
        assert np.array_equal(b[k], a[k]), k
    kp = lambda arr: np.einsum("kc,kcd->kd", arr["keypoint_weights"], arr["template"][arr["keypoint_vertices"]])  # noqa: E731
    surf = a["keypoint_joint"] < 0
    assert np.abs(kp(b)[surf] - kp(a)[surf]).max() < 1e-6
    assert np.abs(b["uvs"][b["faces_uv"]] - a["uvs"][a["faces_uv"]]).max() < 1e-6  # every corner's UV kept


def test_midpoint_model_loads_and_poses_like_the_original(midpoint, model):
    path, report = midpoint
    m2 = blsm.load(path)
    assert m2.num_vertices == 28002 and m2.num_shape_coeffs == model.num_shape_coeffs
    assert report["coverage"]["coincident_fraction"] == 1.0
    corners, bary = read_correspondence(path)
    dist = np.load(path)["reparam_distance"]
    res = posed_check(model, m2, corners, bary, dist, num=4, seed=3)
    assert res["joints_max_mm"] < 1e-3 and res["coinciding_vertices"] == 28002
    assert res["coinciding_mean_mm"] < 0.5 and res["coinciding_within_1mm"] > 0.95
    with torch.no_grad():  # the first 7002 vertices are the old ones: there LBS agrees exactly
        x = torch.randn(2, 47)
        v1, v2 = model(pose=x).vertices, m2(pose=x).vertices
    assert (v2[:, :7002] - v1).abs().max() < 1e-5


def test_shape_space_metrics_on_a_known_space():
    from blsm.learn.reparam.mapping import shape_space_pca

    rng = np.random.default_rng(4)
    basis = np.zeros((3, 10, 3))
    basis[0, :, 0], basis[1, :, 1], basis[2, :, 2] = 0.03, 0.02, 0.01  # orthogonal, known variances
    space = shape_space_pca(np.zeros((10, 3)), basis)
    assert np.allclose(compactness(space), np.cumsum([9, 4, 1]) / 14)
    x = rng.normal(size=(5, 3)) @ basis.reshape(3, -1)  # instances in the space: no error at k = 3
    g = generalisation(space, x.reshape(5, 10, 3), [1, 2, 3])
    assert g[2] < 1e-9 and g[0] > g[1] > g[2]
    s = specificity(space, x.reshape(5, 10, 3), [1, 3], samples=50)
    assert np.all(s > 0)


def _obj(path, v, f):
    path.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in v) + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f))
    return path


def test_cli_bad_templates_exit_2_naming_the_file(packaged, tmp_path, capsys):
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    a = packaged.arrays
    keep = a["template"][a["faces"]].mean(1)[:, 0] > 0  # only the body's left half
    half = _obj(tmp_path / "half.obj", a["template"], a["faces"][keep])
    for bad, words in ((empty, "empty template"), (half, "does not cover")):
        out = tmp_path / "out.npz"
        assert main(["reparam", "default", str(bad), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and str(bad) in err[0] and words in err[0], err
        assert not out.exists()
    assert main(["reparam", "default", str(tmp_path / "missing.obj"), "--out", str(tmp_path / "o.npz")]) == 2
    assert "missing.obj" in capsys.readouterr().err


def test_cli_writes_a_loadable_model(midpoint, tmp_path, capsys):
    path, _ = midpoint
    src = tmp_path / "mid.obj"
    m2 = blsm.load(path)
    _obj(src, m2.template.numpy().astype(np.float64), m2.faces.numpy())
    out = tmp_path / "again.npz"
    assert main(["reparam", "default", str(src), "--out", str(out), "--shape-space", "eq35"]) == 0
    m3 = blsm.load(out)
    assert m3.num_vertices == 28002 and m3.num_shape_coeffs in (64, 65)  # Eq. 3.5: K + 1 (the last ~0 here)
    assert main(["reparam", "default", str(src), "--out", str(out)]) == 2  # exists, no --overwrite
    assert "exists" in capsys.readouterr().err
