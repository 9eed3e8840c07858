"""The learnt landmark detector (blsm.pose2d.landmark_net), its training (blsm.learn.markerless.landmark_detector)
and markerless landmarks (blsm.learn.markerless.landmarks), on tiny renders."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from blsm.learn.markerless.keypoints import MarkerlessConfig
from blsm.learn.markerless.landmarks import LandmarkDetectionConfig, detect_landmarks, with_landmarks
from blsm.learn.markerless.multiview import ViewConfig
from blsm.learn.scans.format import Scan, landmark_names, landmark_points, save_scan
from blsm.pose2d import landmark_net as N


@pytest.fixture(scope="module")
def body(coloured_body):
    """A posed body of the packaged model as a coloured scan with exact ground truth."""
    return coloured_body(4, 2.0)


class _Projecting:
    """Stand-in of LandmarkDetector: the true landmarks projected, pixel noise, a flipped view."""

    def __init__(self, points: np.ndarray, peak: float = 0.9, flip_view: int | None = None) -> None:
        self.points, self.peak, self.flip_view = points, peak, flip_view
        self.names = landmark_names()
        self.name = "projecting"

    def __call__(self, images, boxes, cameras):
        rng = np.random.default_rng(0)
        out = []
        for i, cam in enumerate(cameras):
            d = np.concatenate(
                [
                    cam.project(self.points) + rng.normal(0, 0.3, (len(self.points), 2)),
                    np.full((len(self.points), 1), self.peak),
                ],
                1,
            )
            out.append(d[N.mirror_index(self.names)] if i == self.flip_view else d)
        return out


def test_mirror_index_pairs_sides():
    names = landmark_names()
    m = N.mirror_index(names)
    assert [m[i] for i in m] == list(range(len(names)))
    assert names[m[names.index("acromion_l")]] == "acromion_r" and m[names.index("head_top")] == names.index(
        "head_top"
    )


def test_crop_maps_image_points_onto_crop_pixels():
    img = np.full((120, 100, 3), 90, np.uint8)
    img[30:32, 70:72] = 255  # a 2x2 dot centred on pixel (71, 31) (corner at integer)
    crop = N.crop_box(np.array([40.0, 10.0, 100.0, 110.0]), 1.25)  # goes outside the image
    assert crop[2] - crop[0] == pytest.approx(125.0) and crop[3] - crop[1] == pytest.approx(125.0)
    out = N.crop_square(img, crop, 125)
    ys, xs = np.nonzero(out[..., 0] > 200)
    assert (xs.mean() + 0.5, ys.mean() + 0.5) == pytest.approx((71.0 - crop[0], 31.0 - crop[1]), abs=0.6)
    assert (out[0, 0] == 90).all()  # outside the image: the background


def test_heatmap_decoding_recovers_sub_cell_positions():
    uv = torch.tensor([[[10.3, 20.7], [33.9, 5.2], [float("nan"), 1.0]]])
    h = N.gaussian_heatmaps(uv, 48, 1.5)
    assert h[0, 2].abs().max() == 0  # no label, no target
    pos, peak = N.decode_heatmaps(h)
    assert torch.allclose(pos[0, :2], uv[0, :2], atol=0.05) and (peak[0, :2] > 0.8).all()


def test_projected_landmarks_triangulate_and_fill_the_scan(model, body):
    truth = landmark_points(torch.as_tensor(body.gt_points)).numpy()
    cfg = LandmarkDetectionConfig(MarkerlessConfig(views=ViewConfig(views=6, resolution=96, spp=1)))
    try:
        res = detect_landmarks(body, _Projecting(truth, flip_view=2), cfg, where="body.npz")
    except RuntimeError as exc:  # no Mitsuba variant here
        pytest.skip(str(exc))
    assert res.per_view.swapped.tolist() == [False, False, True, False, False, False]
    err = np.linalg.norm(res.points - truth, axis=1)  # 0.3 px of noise is about 7 mm at 96 px
    assert np.nanmax(err) < 0.03 and np.median(err) < 0.012
    scan = with_landmarks(body, res, "body.npz")
    assert scan.landmark_names == landmark_names() and np.isfinite(scan.landmarks).all()
    assert scan.meta["landmarks_from"]["located"] == len(truth) and body.landmarks.shape == (0, 3)
    with pytest.raises(ValueError, match=r"^body\.npz: no person found in any of the 6 views$"):
        detect_landmarks(body, _Projecting(truth, peak=0.1), cfg, where="body.npz")


def test_training_learns_and_the_file_round_trips(tmp_path, model, body):
    from blsm.learn.markerless import landmark_detector as T

    for i, angle in enumerate((0.0, 1.5)):  # two "population" scans
        c, s = np.cos(angle), np.sin(angle)
        v = body.vertices @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], np.float32).T
        save_scan(
            Scan(**{**body.__dict__, "vertices": v, "gt_points": v, "meta": {"id": f"b{i}"}}),
            tmp_path / "pop" / "scans" / f"b{i}.npz",
        )
    views = ViewConfig(views=8, resolution=96, spp=1)
    try:
        data = T.make_training_views([tmp_path / "pop"], tmp_path / "v.npz", views=views, log=lambda m: None)
    except RuntimeError as exc:
        pytest.skip(str(exc))
    neg = T.make_negative_views(1, tmp_path / "n.npz", len(landmark_names()), views=views)
    with np.load(data) as z:
        assert z["images"].shape == (16, 96, 96, 3) and z["uv"].shape == (16, len(landmark_names()), 2)
    cfg = T.DetectorTrainConfig(
        size=64, epochs=4, batch=4, lr=3e-3, val_fraction=0.34, widths=(8, 16, 16, 32, 32)
    )
    torch.set_num_threads(1)
    report = T.train_detector([data, neg], tmp_path / "d.pt", cfg, log=lambda m: None)
    losses = [e["loss"] for e in report["epochs"]]
    assert losses[-1] < 0.7 * losses[0]
    det = N.LandmarkDetector(tmp_path / "d.pt")
    with np.load(data) as z:
        found = det(list(z["images"][:3]), z["boxes"][:3])
    assert len(found) == 3 and found[0].shape == (len(landmark_names()), 3)
    assert ((found[0][:, 2] >= 0) & (found[0][:, 2] <= 1)).all()


def test_bad_detector_file_and_nobody_are_one_line_errors(tmp_path, capsys):
    from blsm import cli

    (tmp_path / "bad.pt").write_bytes(b"not a file")
    with pytest.raises(ValueError, match=r"bad\.pt: not a landmark detector file"):
        N.load_detector(tmp_path / "bad.pt")
    import trimesh

    box = trimesh.creation.box(extents=(0.5, 1.0, 0.4))
    box.visual.vertex_colors = np.tile([200, 60, 60, 255], (len(box.vertices), 1))
    box.export(tmp_path / "box.ply")
    net = N.LandmarkNet(len(landmark_names()), (8, 16, 16, 32, 32))
    with torch.no_grad():
        net.head.bias.fill_(-5.0)  # a detector that finds nothing
        net.head.weight.zero_()
    N.save_detector(
        net,
        tmp_path / "none.pt",
        {"names": landmark_names(), "size": 64, "growth": 1.25, "widths": [8, 16, 16, 32, 32]},
    )
    for extra, msg in (
        (
            ["--landmark-detector", str(tmp_path / "none.pt"), "--views", "4"],
            "box.ply: no person found in any of the 4 views",
        ),
        (["--landmark-detector", str(tmp_path / "bad.pt")], "bad.pt: not a landmark detector file"),
        ([], "landmark_detector.pt: no packaged landmark detector"),
    ):
        cmd = ["register", str(tmp_path / "box.ply"), "--out", str(tmp_path / "o"), "--detector", "landmarks"]
        assert cli.main([*cmd, *extra]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and msg in err[0], err
        assert not (tmp_path / "o").exists()


def test_cli_registers_from_detected_landmarks(tmp_path, model, body, monkeypatch):
    """`blsm register --detector landmarks` end to end, the detector replaced by exact projections."""
    from blsm import cli
    from blsm.learn.registration.registrations import load_registration

    truth = landmark_points(torch.as_tensor(body.gt_points)).numpy()
    monkeypatch.setattr(N, "LandmarkDetector", lambda *a, **k: _Projecting(truth))
    path = save_scan(body, tmp_path / "body.npz")  # no landmarks, coloured
    cmd = ["register", str(path), "--out", str(tmp_path / "o"), "--detector", "landmarks", "--views", "6"]
    try:
        assert cli.main(cmd) == 0
    except RuntimeError as exc:  # no Mitsuba variant here
        pytest.skip(str(exc))
    reg = load_registration(tmp_path / "o" / "body.npz")
    err = np.linalg.norm(reg.vertices - body.gt_points, axis=1).mean()
    assert err < 0.01, err
