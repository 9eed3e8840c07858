"""The validator's correspondence check (issue 34): the single-precision correspondences of a far
person seen with a long lens pass, one moved by 0.1 px fails.

The labels are made as the generator makes them: Mitsuba's label pass (one ray through every pixel
centre, as ``synth.render``'s ``label_sensor``) gives each hit's position and face, and
:func:`synth.labels.assign_hits` its barycentrics, stored as float32. The check is
:func:`synth.validate.check_correspondences` (what ``synth validate`` runs on every person) with the
camera as the sample's JSON stores it (6 decimals).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from blsm.camera import Camera, look_at_camera
from synth.camera import CameraConfig, sample_camera
from synth.dataset import format as fmt
from synth.labels import assign_hits
from synth.validate import check_correspondences

SIZE = 64
OLD_REPROJ_PX = 0.01  # the fixed tolerance the check had before issue 34


@pytest.fixture(scope="module")
def body(model):
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        out = model(pose=0.6 * torch.randn(1, 47, generator=g), global_orient=torch.tensor([[0.1, 0.7, 0.0]]))
    verts = out.vertices[0].numpy().astype(np.float32)  # as the renderer gets them
    keypoints = dict(zip(model.keypoint_names, out.keypoints[0].numpy()))
    return verts, model.faces.numpy().astype(np.int64), keypoints


@pytest.fixture(scope="module")
def mi():
    from blsm.mitsuba_util import load_mitsuba, resolve_variant

    return load_mitsuba(resolve_variant(None))


def label_pass(mi, verts: np.ndarray, faces: np.ndarray, cam: Camera) -> tuple[np.ndarray, ...]:
    """``corr``, ``depth`` and the person's pixels (bool) of one mesh, as the generator labels them."""
    from blsm.mitsuba_util import sensor_params, to_world_matrix

    mesh = mi.Mesh("person", len(verts), len(faces))
    p = mi.traverse(mesh)
    p["vertex_positions"] = mi.Float(np.ascontiguousarray(verts, np.float32).reshape(-1))
    p["faces"] = mi.UInt32(faces.astype(np.uint32).reshape(-1))
    p.update()
    x_fov, ppx, ppy = sensor_params(cam)
    sensor = {
        "type": "perspective", "fov": x_fov, "fov_axis": "x", "near_clip": 0.01, "far_clip": 1000.0,
        "principal_point_offset_x": ppx, "principal_point_offset_y": ppy,
        "to_world": mi.ScalarTransform4f(to_world_matrix(cam)),
        "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
        "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height, "pixel_format": "rgb",
                 "rfilter": {"type": "box"}},
    }  # fmt: skip
    scene = mi.load_dict({"type": "scene", "sensor": sensor, "person": mesh})
    aovs = mi.load_dict({"type": "aov", "aovs": "dd:depth,pos:position,pi:prim_index"})
    aov = np.asarray(mi.TensorXf(mi.render(scene, integrator=aovs, spp=1)))
    hit = aov[..., 0] > 0.0
    face = np.where(hit, np.rint(aov[..., 4]).astype(np.int64), -1)
    who, bary = assign_hits(SimpleNamespace(hit=hit, face=face, position=aov[..., 1:4]), [(verts, faces)])
    sel = who == 0
    corr = np.zeros((*hit.shape, 3), np.float32)
    corr[..., 0] = np.where(sel, face, -1)
    corr[..., 1:] = np.where(sel[..., None], bary[..., 1:], 0.0)
    depth = np.zeros(hit.shape, np.float32)
    depth[sel] = (aov[..., 1:4][sel].astype(np.float64) @ cam.R[2] + cam.t[2]).astype(np.float32)
    return corr, depth, sel


def stored(cam: Camera) -> Camera:
    """The camera as the sample's JSON holds it."""
    K, R, t = (np.array(fmt.json_round(a)) for a in (cam.K, cam.R, cam.t))
    return Camera(K=K, R=R, t=t, width=cam.width, height=cam.height)


def reprojection(cam: Camera, verts: np.ndarray, faces: np.ndarray, corr: np.ndarray, sel: np.ndarray):
    """Per pixel of ``sel``: the reprojection error (px), the tolerance, cos of the viewing angle."""
    tri = verts.astype(np.float64)[faces[corr[..., 0][sel].astype(np.int64)]]
    bc = corr[..., 1:][sel].astype(np.float64)
    pts = np.einsum("nkc,nk->nc", tri, np.concatenate([1 - bc.sum(1, keepdims=True), bc], 1))
    ys, xs = np.nonzero(sel)
    err = np.abs(cam.project(pts) - np.stack([xs + 0.5, ys + 0.5], 1)).max(1)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ray = pts - cam.center
    cos = np.abs((n * ray).sum(1)) / (np.linalg.norm(n, axis=1) * np.linalg.norm(ray, axis=1))
    return err, fmt.correspondence_tolerance(pts, n, cam.K, cam.R, cam.t), cos


def long_lens(verts: np.ndarray, seed: int) -> tuple[Camera, dict]:
    """The generator's camera sampler with a 400-600 mm lens and the person half the image high."""
    cfg = CameraConfig(
        width=SIZE, height=SIZE, focal_mm=(400.0, 600.0), fill=(0.45, 0.6), rare_rate=0.0, truncation_rate=0.0
    )
    return sample_camera(verts, cfg, np.random.default_rng(seed))


def move(cam: Camera, verts: np.ndarray, faces: np.ndarray, corr: np.ndarray, depth: np.ndarray, x, y, d):
    """Move pixel (x, y)'s correspondence to where the ray through its centre + ``d`` px meets its
    face, and its depth with it (so that only the reprojection is wrong)."""
    v = verts.astype(np.float64)[faces[int(corr[y, x, 0])]]
    ray = cam.R.T @ np.linalg.solve(cam.K, [x + 0.5 + d[0], y + 0.5 + d[1], 1.0])
    n = np.cross(v[1] - v[0], v[2] - v[0])
    p = cam.center + ray * (n @ (v[0] - cam.center)) / (n @ ray)
    b12 = np.linalg.lstsq(np.stack([v[1] - v[0], v[2] - v[0]], 1), p - v[0], rcond=None)[0]
    corr[y, x, 1:] = b12.astype(np.float32)
    depth[y, x] = cam.world_to_camera(p[None])[0, 2]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_far_person_seen_with_a_long_lens_validates(mi, body, seed):
    verts, faces, _ = body
    cam, info = long_lens(verts, seed)
    assert info["distance"] > 30.0 and info["focal_mm"] >= 400.0
    corr, depth, sel = label_pass(mi, verts, faces, cam)
    st = stored(cam)
    assert sel.sum() > 150
    assert check_correspondences(st, verts.astype(np.float64), faces, corr, depth, sel) == []
    err, tol, cos = reprojection(st, verts, faces, corr, sel)
    assert err.max() > 1e-5  # single precision, not exact
    # Still tight: wherever the surface is within 60 degrees of facing the camera, tighter than
    # the old fixed 0.01 px, and below 0.1 px unless seen within a few degrees of edge-on.
    assert (cos > 0.5).sum() > 100 and tol[cos > 0.5].max() < OLD_REPROJ_PX
    assert tol[cos > 0.1].max() < 0.1


@pytest.mark.parametrize("seed, d", [(0, (0.1, 0.0)), (1, (0.0, -0.1)), (2, (-0.1, 0.07))])
def test_a_correspondence_moved_by_01_px_fails(mi, body, seed, d):
    verts, faces, _ = body
    cam, _ = long_lens(verts, seed)
    corr, depth, sel = label_pass(mi, verts, faces, cam)
    st = stored(cam)
    _, tol, cos = reprojection(st, verts, faces, corr, sel)
    ys, xs = np.nonzero(sel)
    k = int(np.flatnonzero(cos > 0.5)[seed * 17])  # a pixel whose surface roughly faces the camera
    move(cam, verts, faces, corr, depth, xs[k], ys[k], d)
    err, _, _ = reprojection(st, verts, faces, corr, sel)
    assert abs(err[k] - 0.1) < 1e-3 and np.delete(err, k).max() < 0.01
    msgs = check_correspondences(st, verts.astype(np.float64), faces, corr, depth, sel)
    assert len(msgs) == 1, msgs
    assert msgs[0].startswith("correspondences reproject 1.00e-01 px from their pixel centres"), msgs
    assert f"pixel ({xs[k]}, {ys[k]})" in msgs[0] and "\n" not in msgs[0]


@pytest.mark.parametrize("keypoint", ["pelvis", "head"])
def test_single_precision_beyond_the_old_fixed_tolerance_passes(mi, body, keypoint):
    """The issue's false alarm: a correct label whose single-precision error, which grows with the
    focal length in pixels, is over the old fixed 0.01 px. A 64 px window of a camera of 500 000 px
    focal length (the window of a 3 m lens on a 24 MP full-frame sensor, 6 um pixels) 50 m away."""
    verts, faces, kp = body
    target = kp[keypoint].astype(np.float64)
    c = look_at_camera(target + [10.0, 8.0, 48.0], target, fov_y_deg=30.0, width=SIZE, height=SIZE)
    f = 5e5
    K = np.array([[f, 0.0, SIZE / 2], [0.0, f, SIZE / 2], [0.0, 0.0, 1.0]])
    cam = Camera(K=K, R=c.R, t=c.t, width=SIZE, height=SIZE)
    corr, depth, sel = label_pass(mi, verts, faces, cam)
    st = stored(cam)
    assert sel.sum() > 1000
    err, tol, _ = reprojection(st, verts, faces, corr, sel)
    assert err.max() > OLD_REPROJ_PX  # what the old check called wrong
    assert check_correspondences(st, verts.astype(np.float64), faces, corr, depth, sel) == []
    assert (err / tol).max() < 0.5


def test_a_wrong_face_fails(mi, body):
    verts, faces, _ = body
    cam, _ = long_lens(verts, 0)
    corr, depth, sel = label_pass(mi, verts, faces, cam)
    st = stored(cam)
    ys, xs = np.nonzero(sel)
    k = len(xs) // 2
    corr[ys[k], xs[k], 0] = (corr[ys[k], xs[k], 0] + 1000) % len(faces)  # another face of the body
    msgs = check_correspondences(st, verts.astype(np.float64), faces, corr, depth, sel)
    here = f"pixel ({xs[k]}, {ys[k]})"
    assert any(m.startswith("correspondences reproject") and here in m for m in msgs), msgs
    corr[ys[k], xs[k], 0] = len(faces)
    msgs = check_correspondences(st, verts.astype(np.float64), faces, corr, depth, sel)
    assert msgs == ["correspondence face index outside the mesh"]
