"""Markerless scan keypoints (blsm.learn.markerless.keypoints, multiview, pose2d) and textured scans, no MediaPipe."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from blsm.camera import look_at_camera
from blsm.learn.markerless import keypoints as M
from blsm.learn.markerless.multiview import ViewConfig, view_boxes, view_cameras
from blsm.learn.scans.format import Scan, load_scan, save_scan
from blsm.pose2d.detectors import MEDIAPIPE_MIRROR, MEDIAPIPE_NAMES, MediaPipeDetector, ProjectedDetector


@pytest.fixture(scope="module")
def body(coloured_body):
    """A posed body of the packaged model as a coloured scan with exact ground truth."""
    return coloured_body(3, 0.7)


def _cameras(n: int = 8):
    rng = np.random.default_rng(1)
    eyes = rng.normal(size=(n, 3))
    eyes = 3.0 * eyes / np.linalg.norm(eyes, axis=1, keepdims=True)
    return [look_at_camera(e, (0.0, 0.0, 0.0), width=200, height=200) for e in eyes]


def test_dlt_recovers_a_point_exactly():
    cams = _cameras()
    X = np.array([0.1, -0.2, 0.05])
    uv = np.stack([c.project(X[None])[0] for c in cams])
    P = M.projection_matrices(cams)
    assert np.abs(M.triangulate_dlt(P, uv) - X).max() < 1e-9
    assert np.abs(M.triangulate_dlt(P[:2], uv[:2]) - X).max() < 1e-9  # two views suffice
    assert M.reprojection_errors(P, uv, X).max() < 1e-6


def test_outlier_rounds_remove_a_gross_outlier_view():
    cams = _cameras(8)
    X = np.array([0.1, 0.3, -0.1])
    P = M.projection_matrices(cams)
    uv = np.stack([c.project(X[None])[0] for c in cams])
    uv[3] += (40.0, -25.0)  # one view detects something else
    plain = M.triangulate_dlt(P, uv)
    robust, kept = M.robust_triangulate(P, uv, M.MarkerlessConfig())
    assert np.linalg.norm(plain - X) > 5e-3  # the outlier matters to Eq. 6.3 alone
    assert np.linalg.norm(robust - X) < 1e-9 and not kept[3]
    assert kept.sum() == 4  # 8 -> 6 -> 5 -> 4 (floor of 25 %, at least one per round)
    assert not M.robust_triangulate(P[:1], uv[:1])[1].any()  # one view: nothing


def test_left_right_flips_are_found_and_undone(model):
    with torch.no_grad():
        kp = model().keypoints[0].double().numpy()
    pts = M.mediapipe_points(kp[[model.keypoint_names.index(n) for n in M.BLSM_NAMES]])
    cams = view_cameras(model.template.numpy(), ViewConfig(views=12, resolution=256))
    boxes = view_boxes(model.template.numpy(), cams)
    flips = ProjectedDetector(pts, noise_px=0.3, flip_rate=0.25, seed=4)
    dets = flips([None] * 12, boxes, cams)
    truth = ProjectedDetector(pts, noise_px=0.3, seed=4)([None] * 12, boxes, cams)
    flipped = np.array([not np.allclose(d, t, equal_nan=True) for d, t in zip(dets, truth, strict=True)])
    assert 0 < flipped.sum() < 6
    res = M.keypoints_from_detections(dets, cams, boxes)
    assert (res.per_view.swapped == flipped).all()
    ok = np.isfinite(res.points).all(1)
    assert ok.all() and np.linalg.norm(res.points - pts[M._MP_INDEX], axis=1).max() < 0.01
    off = M.keypoints_from_detections(dets, cams, boxes, M.MarkerlessConfig(swap_check=False))
    assert not off.per_view.swapped.any()
    assert list(MEDIAPIPE_MIRROR[:3]) == [0, 4, 5] and MEDIAPIPE_NAMES[MEDIAPIPE_MIRROR[11]] == "right_shoulder"


def test_fake_detector_pipeline_on_a_small_render(model, body):
    truth = M.true_keypoints(body, model)
    cfg = M.MarkerlessConfig(views=ViewConfig(views=6, resolution=96, spp=4))
    det = ProjectedDetector(M.mediapipe_points(truth), noise_px=0.3, dropout=0.1, seed=2)
    try:
        res = M.scan_keypoints(body, det, cfg, where="body.npz", keep_images=True)
    except RuntimeError as exc:  # no Mitsuba variant here
        pytest.skip(str(exc))
    assert res.names == list(M.BLSM_NAMES) and res.views == 6 == res.views_with_person
    err = np.linalg.norm(res.points - truth, axis=1)
    assert np.nanmax(err) < 0.03 and np.isfinite(err).sum() >= 18
    assert (res.confidence[np.isfinite(err)] > 0.5).all()
    # The renders agree with the cameras: the true torso keypoints project onto the body, not the background.
    bg = np.round(np.array(cfg.views.background) * 255)
    torso = truth[[M.BLSM_NAMES.index(n) for n in ("left_hip", "right_hip", "left_shoulder", "right_shoulder")]]
    for img, K, R, t in zip(res.images, res.per_view.K, res.per_view.R, res.per_view.t, strict=True):
        uv = (torso @ R.T + t) @ K.T
        cols = img[(uv[:, 1] / uv[:, 2]).astype(int), (uv[:, 0] / uv[:, 2]).astype(int)]
        assert (np.abs(cols.astype(float) - bg).max(1) > 20).mean() >= 0.5
    with pytest.raises(ValueError, match=r"^body\.npz: no person found in any of the 6 views$"):
        M.scan_keypoints(body, ProjectedDetector(M.mediapipe_points(truth), all_missing=True), cfg, where="body.npz")


def test_render_views_and_cameras(body):
    cfg = ViewConfig(views=20, resolution=64, min_elevation_deg=-15.0, max_elevation_deg=55.0)
    cams = view_cameras(body.vertices, cfg)
    el = np.degrees(np.arcsin([(c.center - body.vertices.mean(0))[1] / np.linalg.norm(c.center - body.vertices.mean(0))
                               for c in cams]))
    assert el.min() > -20 and el.max() < 60  # no steep view from below the floor
    boxes = view_boxes(body.vertices, cams)
    assert ((boxes[:, 2] - boxes[:, 0]) > 5).all() and (boxes[:, [2, 3]] <= 64).all()
    with pytest.raises(ValueError):
        ViewConfig(views=1)


def test_colours_round_trip(tmp_path, body):
    path = save_scan(body, tmp_path / "a.npz")
    back = load_scan(path)
    assert back.colors.dtype == np.uint8 and (back.colors == body.colors).all()
    assert np.allclose(back.gt_joints, body.gt_joints)
    floats = Scan(**{**body.__dict__, "colors": body.colors / 255.0})
    assert (load_scan(save_scan(floats, tmp_path / "b.npz")).colors == body.colors).all()
    import trimesh

    for ext in ("ply", "obj"):
        mesh = trimesh.Trimesh(body.vertices, body.faces, vertex_colors=body.colors, process=False)
        mesh.export(tmp_path / f"c.{ext}")
        assert (load_scan(tmp_path / f"c.{ext}").colors == body.colors).all()
    with pytest.raises(ValueError, match="colors must be"):
        save_scan(Scan(**{**body.__dict__, "colors": body.colors[:5]}), tmp_path / "d.npz")
    plain = trimesh.Trimesh(body.vertices, body.faces, process=False)
    plain.export(tmp_path / "e.ply")
    assert load_scan(tmp_path / "e.ply").colors is None


def test_mediapipe_detector_without_environment(tmp_path, body, capsys, monkeypatch):
    with pytest.raises(ValueError, match="setup_reference.sh"):
        MediaPipeDetector(python=str(tmp_path / "none" / "python"))([np.zeros((8, 8, 3), np.uint8)], np.zeros((1, 4)))
    from blsm import cli

    monkeypatch.setenv("BLSM_POSE_ENV", str(tmp_path / "nowhere"))
    scan = save_scan(body, tmp_path / "s.npz")
    assert cli.main(["scan-keypoints", str(scan), "--out", str(tmp_path / "k.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nowhere" in err[0] and "setup_reference.sh" in err[0]
    assert not (tmp_path / "k.json").exists()
    assert cli.main(["scan-keypoints", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "k.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing.npz: scan file does not exist" in err[0]


def test_stool_and_floor_markers_keep_clear_of_the_body():
    from blsm.learn.scans import scan_paint

    rng = np.random.default_rng(0)
    body = rng.uniform([-0.2, 0.0, -0.15], [0.2, 1.7, 0.15], size=(3000, 3))
    v, f, c = scan_paint.stool_mesh(body, 0.0, rng)
    assert abs(v[:, 1].min()) < 1e-9 and v[:, 1].max() == pytest.approx(0.45)
    centre = 0.5 * (v.min(0) + v.max(0))
    assert np.linalg.norm(body[:, [0, 2]] - centre[[0, 2]], axis=1).min() > 0.17 + 0.03 - 1e-9
    import trimesh

    assert trimesh.Trimesh(v, f).is_watertight and trimesh.Trimesh(v, f).volume > 0 and c.shape == (len(v), 3)
    mv, mf, mc = scan_paint.floor_markers(body, 0.0, 5, rng)
    assert mv[:, 1].max() < 0.004 and len(mv) == 5 * len(mv) // 5 and len(mc) == len(mv)
    allv, allf, allc, ranges = scan_paint.add_props(body[:3], np.array([[0, 1, 2]]), np.zeros((3, 3), np.uint8),
                                                     body, True, 5, rng)
    assert ranges["stool"][0] == 3 and ranges["floor_markers"][1] == len(allv) and allf.max() < len(allv)


@pytest.mark.slow
def test_population_colours_and_artefacts(tmp_path, model):
    """Colours and props come from their own random streams: the body arrays are unchanged."""
    from blsm.learn.scans.population import Artefacts, make_population

    make_population(tmp_path / "a", 1, 1, 1, seed=5, model=None, colors=False)
    make_population(tmp_path / "b", 1, 1, 1, seed=5, artefacts=Artefacts(stool=True, floor_markers=3))
    make_population(tmp_path / "c", 1, 1, 1, seed=5, artefacts=Artefacts(missing_feet=True))
    for name in ("s00000_00", "s00000_01"):
        a, b, c = (load_scan(tmp_path / x / "scans" / f"{name}.npz") for x in "abc")
        assert a.colors is None and b.colors.shape == (len(b.vertices), 3)
        n = len(a.vertices)
        assert b.meta["props"]["stool"][0] == n and b.meta["props"]["floor_markers"][1] == len(b.vertices)
        assert (b.vertices[:n] == a.vertices).all() and (b.faces[: len(a.faces)] == a.faces).all()
        assert (b.landmarks[np.isfinite(a.landmarks)] == a.landmarks[np.isfinite(a.landmarks)]).all()
        assert (b.gt_points == a.gt_points).all() and a.gt_joints.shape == (20, 3)
        assert len(c.vertices) < n - 1000 and c.meta["artefacts"]["feet"] > 1000
        # the true joints: a rest scan's hip joints sit where the model's skeleton puts them, to a few cm
        if name.endswith("_00"):
            assert np.linalg.norm(a.gt_joints - model.heads.numpy(), axis=1).max() < 0.15
