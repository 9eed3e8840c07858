from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from blsm.learn.scans import landmarks as L
from blsm.learn.scans.format import (
    Scan,
    landmark_names,
    landmark_points,
    load_scan,
    save_scan,
    template_landmarks,
)


@pytest.fixture(scope="module")
def table(model):
    names, idx, w = template_landmarks(model)
    t = model.template.numpy()
    return {n: t[i[0]] for n, i in zip(names, idx.numpy(), strict=True)}, names, idx


def _tetra_scan(names=("sellion", "crotch")) -> Scan:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32)
    lm = np.array([[0.1, 0.2, 0.3], [np.nan] * 3], np.float32)[: len(names)]
    return Scan(v, f, list(names), lm, {"id": "tetra"})


# ---- landmark table ----


def test_yaml_equals_rules():
    import blsm
    from blsm.model import DEFAULT_RIG

    rules = L.compute_landmarks(blsm.load(DEFAULT_RIG))  # landmarks are defined on the rig's template
    assert L.LANDMARKS_YAML.read_text() == L.to_yaml(rules)
    assert 60 <= len(rules) <= 90


def test_landmarks_distinct_and_on_their_side(model, table):
    pos, names, idx = table
    vert = idx[:, 0].tolist()
    shared = {v for v in vert if vert.count(v) > 1}
    assert not shared, [n for n, v in zip(names, vert, strict=True) if v in shared]
    # Back landmarks lie behind their front partners at the same height (a front and a back
    # landmark once fell on one vertex because the midline band held only the front vertex).
    for back, front in (("back_t10", "substernale"), ("back_t8", "substernale"), ("back_waist", "omphalion"),
                        ("cervicale", "suprasternale")):
        assert pos[back][2] < pos[front][2] - 0.08, (back, front)
    assert abs(pos["back_t10"][1] - pos["substernale"][1]) < 0.012


def test_pairs_mirror_and_sides(model, table):
    pos, names, idx = table
    mirror = model.vertex_mirror.numpy()
    vert = dict(zip(names, idx[:, 0].tolist(), strict=True))
    for n in names:
        if n.endswith("_l"):
            r = n[:-2] + "_r"
            assert vert[r] == mirror[vert[n]], n
            assert pos[n][0] > 0.0 and pos[r][0] < 0.0, n
            np.testing.assert_allclose(pos[r], pos[n] * [-1, 1, 1], atol=1e-6)
        elif not n.endswith("_r"):
            assert pos[n][0] == 0.0, n


def test_anatomical_order(model, table):
    p, _, _ = table
    y = {n: v[1] for n, v in p.items()}
    assert max(y, key=y.get) == "head_top"
    chain = [
        "head_top",
        "sellion",
        "suprasternale",
        "substernale",
        "omphalion",
        "crotch",
        "femoral_lat_epicondyle_l",
        "lateral_malleolus_l",
    ]
    for a, b in zip(chain, chain[1:], strict=False):
        assert y[a] > y[b], (a, b)
    assert y["glabella"] > y["sellion"] > y["pronasale"] > y["menton"]
    assert p["pronasale"][2] > p["sellion"][2]
    # Acromion lateral of the neck; dactylion farther from the elbow than the styloids.
    assert p["acromion_l"][0] > p["tragion_l"][0] + 0.05
    el = model.heads[model.bone_names.index("elbow_l")].numpy()
    d = {n: np.linalg.norm(p[n] - el) for n in ("dactylion_l", "radial_styloid_l", "ulnar_styloid_l")}
    assert d["dactylion_l"] > d["radial_styloid_l"] + 0.1 and d["dactylion_l"] > d["ulnar_styloid_l"] + 0.1
    assert p["lateral_malleolus_l"][0] > p["medial_malleolus_l"][0]
    assert p["femoral_lat_epicondyle_l"][0] > p["femoral_med_epicondyle_l"][0]
    assert p["toe_tip_l"][2] > p["mtp1_l"][2] > p["heel_l"][2]
    assert p["cervicale"][2] < p["suprasternale"][2]  # C7 at the back
    assert p["psis_l"][2] < p["asis_l"][2]


def test_landmark_points_is_selection(model, table):
    _, names, idx = table
    v = model.template[None].repeat(2, 1, 1).clone().requires_grad_(True)
    pts = landmark_points(v)
    assert pts.shape == (2, len(names), 3)
    torch.testing.assert_close(pts[0], model.template[idx[:, 0]])
    pts.sum().backward()
    assert v.grad.abs().sum() == pytest.approx(2 * 3 * len(names))
    assert landmark_points(model.template).shape == (len(names), 3)
    with pytest.raises(ValueError, match="topology"):
        landmark_points(torch.zeros(2, 10, 3))


# ---- files ----


def test_npz_round_trip(tmp_path):
    scan = _tetra_scan()
    scan.gt_angles = np.zeros(47, np.float32)
    path = save_scan(scan, tmp_path / "a.npz")
    back = load_scan(path)
    np.testing.assert_array_equal(back.vertices, scan.vertices)
    np.testing.assert_array_equal(back.faces, scan.faces)
    np.testing.assert_array_equal(back.landmarks, scan.landmarks)
    assert back.landmark_names == ["sellion", "crotch"]
    assert back.located.tolist() == [True, False]
    assert back.meta == {"id": "tetra"} and back.gt_points is None and back.gt_angles.shape == (47,)


def test_mesh_with_landmark_json(tmp_path):
    import trimesh

    scan = _tetra_scan()
    for ext in ("obj", "ply", "glb"):
        path = tmp_path / f"m.{ext}"
        trimesh.Trimesh(scan.vertices, scan.faces, process=False).export(path)
        (tmp_path / "m.landmarks.json").write_text(json.dumps({"sellion": [0.1, 0.2, 0.3], "crotch": None}))
        back = load_scan(path, require_landmarks=True)
        assert back.vertices.shape == (4, 3) and back.faces.shape == (4, 3), ext
        np.testing.assert_allclose(back.landmarks[0], [0.1, 0.2, 0.3], atol=1e-6)
        assert np.isnan(back.landmarks[1]).all()
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"crotch": [0, 0, 0]}))
    assert load_scan(tmp_path / "m.obj", landmarks=other).landmark_names == ["crotch"]


def test_bad_inputs(tmp_path):
    import trimesh

    def bad(scan: Scan, match: str, **kw) -> None:
        with pytest.raises(ValueError, match=match):
            save_scan(scan, tmp_path / "x.npz")
        assert not (tmp_path / "x.npz").exists()

    s = _tetra_scan()
    s.vertices[1, 0] = np.nan
    bad(s, "NaN or inf")
    s = _tetra_scan()
    s.faces[0, 0] = 9
    bad(s, "outside")
    s = _tetra_scan()
    s.faces = np.concatenate([s.faces, [[0, 1, 2]]]).astype(np.int32)  # edge 0-1 in three faces
    bad(s, "non-manifold")
    s = _tetra_scan()
    s.landmarks[1, 0] = 0.5  # a partly NaN row
    bad(s, "landmarks hold NaN")
    bad(_tetra_scan(("sellion", "not_a_landmark")), "unknown landmark")
    s = _tetra_scan()
    s.vertices, s.faces = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)
    bad(s, "empty mesh")
    # Open borders are fine.
    s = _tetra_scan()
    s.faces = s.faces[:3]
    save_scan(s, tmp_path / "open.npz")
    # require_landmarks with no located landmark.
    s = _tetra_scan(("crotch",))
    s.landmarks[:] = np.nan
    save_scan(s, tmp_path / "nolm.npz")
    with pytest.raises(ValueError, match="nolm.npz: scan has no located landmarks"):
        load_scan(tmp_path / "nolm.npz", require_landmarks=True)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="junk.npz: not a readable .npz scan file"):
        load_scan(tmp_path / "junk.npz")
    np.savez(tmp_path / "other.npz", format="blsm-model")
    with pytest.raises(ValueError, match="other.npz: not a BLSM scan file"):
        load_scan(tmp_path / "other.npz")
    with pytest.raises(ValueError, match="does not exist"):
        load_scan(tmp_path / "missing.obj")
    trimesh.Trimesh(_tetra_scan().vertices, _tetra_scan().faces).export(tmp_path / "m.obj")
    (tmp_path / "m.landmarks.json").write_text("[1, 2")
    with pytest.raises(ValueError, match="m.landmarks.json: bad landmark file"):
        load_scan(tmp_path / "m.obj")
    with pytest.raises(ValueError, match="unknown scan file type"):
        load_scan(tmp_path / "m.landmarks.json")


def test_names_known():
    names = landmark_names()
    assert "sellion" in names and "acromion_l" in names and "acromion_r" in names
    assert len(set(names)) == len(names)


def test_landmarks_command_rewrites_the_packaged_table(tmp_path):
    """``python -m blsm.learn.scans.landmarks --out FILE`` writes the packaged table again, unchanged."""
    assert L.main(["--out", str(tmp_path / "lm.yaml")]) == 0
    assert (tmp_path / "lm.yaml").read_text() == L.LANDMARKS_YAML.read_text()
