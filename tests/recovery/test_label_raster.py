from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from recovery.utils import raster
from recovery.utils.raster import rasterize, rasterize_labels, rasterize_labels_batch

K = np.array([[30.0, 0.0, 12.0], [0.0, 30.0, 12.0], [0.0, 0.0, 1.0]])
W = H = 24


def _ray_cast(verts: np.ndarray, faces: np.ndarray, k: np.ndarray, width: int, height: int, near=1e-3):
    """Brute force: per pixel, intersect the ray through its centre with every face (Moller-Trumbore)."""
    face_index = np.full((height, width), -1)
    depth = np.full((height, width), np.inf)
    k_inv = np.linalg.inv(k)
    for y in range(height):
        for x in range(width):
            ray = k_inv @ np.array([x + 0.5, y + 0.5, 1.0])  # z component 1: hit distance t is depth z
            for f, (a, b, c) in enumerate(verts[faces]):
                if min(a[2], b[2], c[2]) <= near:
                    continue
                e1, e2 = b - a, c - a
                p = np.cross(ray, e2)
                det = e1 @ p
                if abs(det) < 1e-15:
                    continue
                s = -a  # ray origin is the camera centre
                u = (s @ p) / det
                qv = np.cross(s, e1)
                v = (ray @ qv) / det
                if u < 0 or v < 0 or u + v > 1:
                    continue
                t = (e2 @ qv) / det
                if t < depth[y, x]:
                    depth[y, x], face_index[y, x] = t, f
    return face_index, depth


def _cube(rotation_seed: int, z: float = 3.0):
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    angles = np.random.default_rng(rotation_seed).random(3)
    rot = trimesh.transformations.random_rotation_matrix(angles)[:3, :3]
    verts = box.vertices @ rot.T + np.array([0.1, -0.2, z])
    normals = box.face_normals
    axis = np.abs(normals).argmax(1)
    side = 1 + 2 * axis + (normals[np.arange(len(axis)), axis] > 0)  # labels 1..6, one per cube side
    return verts, np.asarray(box.faces), side


def test_single_triangle_covers_exactly_the_pixel_centres_inside_it():
    uv = np.array([[3.2, 2.7], [20.9, 8.1], [7.4, 21.3]])  # image coordinates (pixels)
    z = 2.0
    verts = np.c_[(uv - K[:2, 2]) / K[0, 0] * z, np.full(3, z)]
    face_index, depth = rasterize(verts, np.array([[0, 1, 2]]), K, W, H)
    inside = np.zeros((H, W), bool)
    for y in range(H):
        for x in range(W):
            p = np.array([x + 0.5, y + 0.5])
            edges = []
            for i in range(3):
                (ex, ey), (px, py) = uv[(i + 1) % 3] - uv[i], p - uv[i]
                edges.append(ex * py - ey * px)
            inside[y, x] = all(e >= 0 for e in edges) or all(e <= 0 for e in edges)
    assert 30 < inside.sum() < W * H // 2
    np.testing.assert_array_equal(face_index >= 0, inside)
    np.testing.assert_allclose(depth[inside], z, rtol=1e-12)
    assert np.isinf(depth[~inside]).all()
    # The other winding covers the same pixels.
    flipped, _ = rasterize(verts, np.array([[0, 2, 1]]), K, W, H)
    np.testing.assert_array_equal(flipped >= 0, inside)


def test_depth_is_perspective_correct_on_a_slanted_triangle():
    verts = np.array([[-1.0, -0.8, 1.5], [1.2, -0.5, 6.0], [0.1, 1.0, 2.5]])
    face_index, depth = rasterize(verts, np.array([[0, 1, 2]]), K, W, H)
    ref_index, ref_depth = _ray_cast(verts, np.array([[0, 1, 2]]), K, W, H)
    hit = ref_index >= 0
    assert hit.sum() > 50
    np.testing.assert_array_equal(face_index, ref_index)
    np.testing.assert_allclose(depth[hit], ref_depth[hit], rtol=1e-10)


@pytest.mark.parametrize("order", [[0, 1], [1, 0]])
def test_the_nearer_of_two_overlapping_triangles_wins_in_either_order(order):
    near_tri = np.array([[-0.4, -0.4, 2.0], [0.4, -0.4, 2.0], [0.0, 0.4, 2.0]])
    far_tri = np.array([[-0.2, -0.6, 3.0], [1.0, -0.6, 3.0], [0.4, 0.6, 3.0]])
    tris = [near_tri, far_tri]
    labels = np.array([5, 9])
    verts = np.concatenate([tris[i] for i in order])
    faces = np.arange(6).reshape(2, 3)
    out = rasterize_labels(verts, faces, K, W, H, labels[order], background=0)
    ref_index, _ = _ray_cast(verts, faces, K, W, H)
    ref = np.where(ref_index >= 0, labels[order][ref_index], 0)
    np.testing.assert_array_equal(out, ref)
    assert (out == 5).sum() > 20 and (out == 9).sum() > 20  # both visible, so the overlap was resolved
    alone_far = rasterize_labels(far_tri, np.array([[0, 1, 2]]), K, W, H, np.array([9]))
    assert ((alone_far == 9) & (out == 5)).sum() > 10  # the far face is hidden where the near one is


def test_equal_depths_keep_the_lowest_face_index_across_chunks(monkeypatch):
    tri = np.array([[-0.4, -0.4, 2.0], [0.4, -0.4, 2.0], [0.0, 0.4, 2.0]])
    verts = np.concatenate([tri, tri])
    faces = np.array([[0, 1, 2], [3, 4, 5]])  # same corner order: bit-identical depths
    face_index, _ = rasterize(verts, faces, K, W, H)
    assert set(np.unique(face_index)) == {-1, 0}
    monkeypatch.setattr(raster, "_CHUNK", 7)  # one face per chunk: the merge between chunks decides
    chunked, _ = rasterize(verts, faces, K, W, H)
    np.testing.assert_array_equal(chunked, face_index)


def test_faces_behind_the_camera_are_dropped():
    tri = np.array([[-0.4, -0.4, 2.0], [0.4, -0.4, 2.0], [0.0, 0.4, 2.0]])
    behind = tri * np.array([1.0, 1.0, -1.0])  # projects into the image through the sign flip of z
    straddling = tri.copy()
    straddling[2, 2] = -0.5
    on_near = tri.copy()
    on_near[0, 2] = 1e-3
    for verts in (behind, straddling, on_near):
        face_index, depth = rasterize(verts, np.array([[0, 1, 2]]), K, W, H)
        assert (face_index == -1).all() and np.isinf(depth).all()
    ok, _ = rasterize(tri, np.array([[0, 1, 2]]), K, W, H)
    assert (ok == 0).sum() > 20


@pytest.mark.parametrize("seed", [1, 2])
def test_cube_labels_and_depth_match_a_per_pixel_ray_test(seed, monkeypatch):
    verts, faces, side = _cube(seed)
    face_index, depth = rasterize(verts, faces, K, W, H)
    ref_index, ref_depth = _ray_cast(verts, faces, K, W, H)
    hit = ref_index >= 0
    assert 100 < hit.sum() < W * H
    # Labels per side: pixels on a side's diagonal may pick either of its two coplanar triangles.
    labels = rasterize_labels(verts, faces, K, W, H, side)
    np.testing.assert_array_equal(labels, np.where(hit, side[ref_index], 0))
    assert len(np.unique(labels)) >= 3  # background and at least two sides seen
    np.testing.assert_allclose(depth[hit], ref_depth[hit], rtol=1e-10)
    monkeypatch.setattr(raster, "_CHUNK", 5)
    np.testing.assert_array_equal(rasterize(verts, faces, K, W, H)[0], face_index)


def test_batch_matches_single_calls_and_takes_torch_input():
    (v1, faces, side), (v2, _, _) = _cube(3), _cube(4, z=4.0)
    batch = rasterize_labels_batch(torch.tensor(np.stack([v1, v2])), torch.tensor(faces), K, W, H, side)
    assert batch.shape == (2, H, W)
    np.testing.assert_array_equal(batch[0], rasterize_labels(v1, faces, K, W, H, side))
    np.testing.assert_array_equal(batch[1], rasterize_labels(v2, faces, K, W, H, side))
    assert not np.array_equal(batch[0], batch[1])
    per_mesh_k = np.stack([K, K * np.array([[0.5], [0.5], [1.0]])])
    half = rasterize_labels_batch(np.stack([v1, v1]), faces, per_mesh_k, W, H, side, background=-1)
    assert (half[1] == -1).sum() > (half[0] == -1).sum()


def test_bad_inputs_raise():
    tri = np.array([[-0.4, -0.4, 2.0], [0.4, -0.4, 2.0], [0.0, 0.4, 2.0]])
    faces = np.array([[0, 1, 2]])
    with pytest.raises(ValueError, match="K"):
        rasterize(tri, faces, np.eye(2), W, H)
    with pytest.raises(ValueError, match="outside"):
        rasterize(tri, np.array([[0, 1, 3]]), K, W, H)
    with pytest.raises(ValueError, match="vertices_cam"):
        rasterize(tri[:, :2], faces, K, W, H)
    with pytest.raises(ValueError, match="width"):
        rasterize(tri, faces, K, 0, H)
    with pytest.raises(ValueError, match="face_labels"):
        rasterize_labels(tri, faces, K, W, H, np.array([1.5]))
