"""Tests of blsm/learn/register.py (thesis Sec. 5.4.1, Eqs. 5.13-5.25)."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from blsm.learn import register as R
from blsm.learn.posing import pose

# ------------------------------------------------------------------------------------------------
# Synthetic scans (also used by the registration benchmark)


def fps_vertices(template: torch.Tensor, n: int) -> np.ndarray:
    """(n,) template vertex indices by farthest-point sampling from the top of the head."""
    v = template.double().numpy()
    idx = [int(np.argmax(v[:, 1]))]
    d = np.linalg.norm(v - v[idx[0]], axis=1)
    for _ in range(n - 1):
        i = int(np.argmax(d))
        idx.append(i)
        d = np.minimum(d, np.linalg.norm(v - v[i], axis=1))
    return np.array(idx)


def subdivide(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One midpoint subdivision: (V, 3), (F, 3) -> (V + E, 3), (4F, 3)."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, inv = np.unique(e, axis=0, return_inverse=True)
    mid = inv.reshape(3, -1).T + len(vertices)  # (F, 3) midpoints of edges 01, 12, 20
    verts = np.concatenate([vertices, 0.5 * (vertices[uniq[:, 0]] + vertices[uniq[:, 1]])])
    a, b, c = faces.T
    ab, bc, ca = mid.T
    new = np.concatenate([np.stack(t, 1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return verts, new


@dataclass
class SynthScan:
    vertices: np.ndarray
    faces: np.ndarray
    landmark_names: list
    landmarks: np.ndarray
    meta: dict
    gt_points: np.ndarray


def synthetic_scan(model, gen: torch.Generator, posed: bool, selection: R.LandmarkSelection,
                   noise: float = 0.001, lm_noise: float = 0.002, holes: bool = True) -> SynthScan:
    """A body of the model's population, rest or posed by the packaged CMU prior, subdivided once,
    with ``noise`` metres of Gaussian vertex noise, holes at the soles and armpits, and landmarks at
    the posed ``selection`` points (+ ``lm_noise``). ``gt_points`` are the clean posed vertices."""
    from blsm.mocap import prior as prior_mod

    k = int(torch.randint(0, model.population_bone.shape[0], (1,), generator=gen))
    go = (torch.rand(1, 3, generator=gen) - 0.5) * 0.6
    tr = torch.rand(1, 3, generator=gen) - 0.5
    kw = {}
    if posed:
        prior = prior_mod.load_prior(Path(prior_mod.__file__).parents[1] / "data" / "pose_prior_cmu.npz")
        seed = int(torch.randint(0, 1 << 30, (1,), generator=gen))
        kw["pose"] = prior.sample(1, generator=torch.Generator().manual_seed(seed)).to(model.template.dtype)
    with torch.no_grad():
        out = model(bone=model.population_bone[k:k + 1], shape=model.population_shape[k:k + 1],
                    global_orient=go.to(model.template.dtype), transl=tr.to(model.template.dtype), **kw)
    gt = out.vertices[0].double().numpy()
    faces = model.faces.numpy()
    t = model.template.double().numpy()
    keep = np.ones(len(faces), bool)
    if holes:
        bad = t[:, 1] < t[:, 1].min() + 0.02  # soles
        for sx in (1, -1):
            k_arm = int(np.argmin(np.linalg.norm(t - np.array([sx * 0.17, 0.28, 0.0]), axis=1)))
            bad |= np.linalg.norm(t - t[k_arm], axis=1) < 0.03  # armpits
        keep = ~bad[faces].any(1)
    used = np.unique(faces[keep])
    remap = -np.ones(len(gt), int)
    remap[used] = np.arange(len(used))
    v, f = subdivide(gt[used], remap[faces[keep]])
    rng = np.random.default_rng(int(torch.randint(0, 1 << 30, (1,), generator=gen)))
    v = v + rng.normal(0, noise, v.shape)
    lms = selection.select(torch.as_tensor(gt)[None])[0].numpy()
    lms = lms + rng.normal(0, lm_noise, lms.shape)
    return SynthScan(v.astype(np.float32), f.astype(np.int32), list(selection.names),
                     lms.astype(np.float32), {"id": "posed" if posed else "rest"}, gt.astype(np.float32))


def write_scan_npz(scan: SynthScan, path: Path, **override) -> Path:
    arrays = dict(format=np.array("blsm-scan"), format_version=np.array(1), vertices=scan.vertices,
                  faces=scan.faces, landmark_names=np.array(scan.landmark_names), landmarks=scan.landmarks,
                  meta=np.array(json.dumps(scan.meta)), gt_points=scan.gt_points)
    arrays.update(override)
    np.savez(path, **arrays)
    return path


@pytest.fixture(autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def selection(model) -> R.LandmarkSelection:
    """The packaged landmark table (blsm/data/landmarks.yaml)."""
    return R.default_selection(model)


# ------------------------------------------------------------------------------------------------
# Stage 1


def test_stage1_recovers_pose_and_scales(model, gen):
    idx = fps_vertices(model.template, 250)
    sel = R.LandmarkSelection.from_index([str(i) for i in idx], idx)
    b_true = 1.0 + 0.15 * (torch.rand(2, model.num_joints, generator=gen) - 0.5)
    x_true = 0.3 * torch.randn(2, model.num_dofs, generator=gen)
    theta_true = R.pose_angles(model, x_true)
    go = torch.tensor([[0.2, 1.0, -0.1], [0.0, -0.5, 0.1]])
    tr = torch.tensor([[0.1, 0.9, -0.3], [-0.2, 1.0, 0.4]])
    with torch.no_grad():
        v_true = pose(model, model.template, bone_scales=b_true, angles=theta_true, global_orient=go, transl=tr).vertices
    lms = sel.select(v_true)
    lms[1, :10] = float("nan")  # unlocated landmarks are ignored
    cfg = R.RegisterConfig(stage1_iterations=800, angle_prior=0.0, scale_prior=0.0, shape_init=False)
    st = R.fit_landmarks(model, lms, sel, cfg)
    assert float(st.landmark_error.max()) < 1e-3  # metres
    v_fit = torch.stack([torch.as_tensor(R.st1_vertices(model, st, n)) for n in range(2)])
    assert float((v_fit - v_true).norm(dim=-1).mean()) < 2e-3
    # Bones carrying enough landmarks recover their scales.
    np.testing.assert_allclose(st.bone_scales[:, :4].numpy(), b_true[:, :4].numpy(), rtol=0.03)
    np.testing.assert_allclose(st.bone_scales[:, 14:].numpy(), b_true[:, 14:].numpy(), rtol=0.03)
    lo, hi = model.dof_limits[:, 0], model.dof_limits[:, 1]
    assert bool(((st.angles >= lo) & (st.angles <= hi)).all())


def test_stage1_bad_input(model, selection):
    sel = selection
    with pytest.raises(ValueError, match="landmarks must be"):
        R.fit_landmarks(model, torch.zeros(1, 5, 3), sel)
    with pytest.raises(ValueError, match="at least 3"):
        R.fit_landmarks(model, torch.full((1, len(sel), 3), float("nan")), sel)
    with pytest.raises(ValueError, match="landmark index"):
        R.LandmarkSelection.from_index(["a", "b"], [1, 2, 3])


# ------------------------------------------------------------------------------------------------
# Operators


def test_mnn_is_mutual_against_brute_force(gen):
    rng = np.random.default_rng(0)
    a, b = rng.random((60, 3)), rng.random((45, 3))
    ia, ib = R.mutual_nearest_neighbours(a, b)
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)
    nab, nba = d.argmin(1), d.argmin(0)
    expect = [(i, nab[i]) for i in range(len(a)) if nba[nab[i]] == i]
    assert list(zip(ia.tolist(), ib.tolist())) == [(int(i), int(j)) for i, j in expect]
    assert 0 < len(expect) < len(b)  # a real subset, so the test can fail both ways
    e1, e2 = R.mutual_nearest_neighbours(a[:0], b)
    assert len(e1) == len(e2) == 0


def _grid(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    ij = torch.stack(torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij"), -1).reshape(-1, 2)
    verts = torch.cat([ij.double() * 0.01, torch.zeros(n * n, 1, dtype=torch.float64)], 1)
    k = torch.arange(n * n).reshape(n, n)
    a, b, c, d = k[:-1, :-1].flatten(), k[1:, :-1].flatten(), k[:-1, 1:].flatten(), k[1:, 1:].flatten()
    faces = torch.cat([torch.stack([a, b, d], 1), torch.stack([a, d, c], 1)])
    return verts, faces


def test_uniform_laplacian_flat_grid():
    verts, faces = _grid(6)
    edges = R.mesh_edges(faces)
    lap = R.uniform_laplacian(verts[None], edges)[0].reshape(6, 6, 3)
    assert float(lap[1:-1, 1:-1].abs().max()) < 1e-12  # Eq. 5.17 vanishes inside a regular grid
    assert float(lap[0, 0].norm()) > 1e-3  # but not at a corner
    bumped = verts.clone()
    bumped[14, 2] = 0.01
    lap_b = R.uniform_laplacian(bumped[None], edges)[0]
    np.testing.assert_allclose(float(lap_b[14, 2]), -0.01, rtol=1e-9)  # all 6 neighbours flat
    # Against the dense matrix form of Eqs. 5.19-5.20.
    n = verts.shape[0]
    adj = torch.zeros(n, n, dtype=torch.float64)
    adj[edges[:, 0], edges[:, 1]] = 1
    adj[edges[:, 1], edges[:, 0]] = 1
    lmat = adj / adj.sum(1, keepdim=True) - torch.eye(n, dtype=torch.float64)
    torch.testing.assert_close(R.uniform_laplacian(bumped[None], edges)[0], lmat @ bumped)


def test_edge_terms_zero_at_stage1_mesh(model, gen):
    edges = R.mesh_edges(model.faces)
    assert edges.shape[0] > model.num_vertices
    s_t = model.template[None] + 0.01 * torch.randn(1, model.num_vertices, 3, generator=gen)
    ev, el = R.edge_terms(s_t, s_t, edges)
    assert float(ev) == 0.0 and float(el) == 0.0
    ev2, el2 = R.edge_terms(s_t * 1.1, s_t, edges)
    assert float(ev2) > 0 and float(el2) > 0
    ev3, _ = R.edge_terms(s_t + torch.tensor([0.1, 0.0, 0.0]), s_t, edges)  # translation keeps edges
    assert float(ev3) < 1e-12


def test_pair_term_point_to_point_and_point_to_plane():
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    r = torch.tensor([[0.003, 0.004, 0.0], [0.0, 0.002, 0.0]], dtype=torch.float64)  # along, across
    assert float(R.pair_term(r, None)) == pytest.approx((0.005**2 + 0.002**2) / 2)  # Eq. 5.15
    assert float(R.pair_term(r, n, 0.0)) == pytest.approx(0.002**2 / 2)  # only the normal part
    assert float(R.pair_term(r, n, 0.5)) == pytest.approx((0.5 * 0.005**2 + 0.002**2) / 2)
    with pytest.raises(ValueError, match="normals"):
        R.pair_term(r, None, 0.0)
    with pytest.raises(ValueError, match="mnn_tangent_weight"):
        R.RegisterConfig(mnn_tangent_weight=1.5)


def test_refine_starts_from_init(model, gen, selection):
    """With zero iterations stage 2 returns its initial V_D, and S^ = S^_T + A V_D (Eq. 12)."""
    scan = synthetic_scan(model, gen, posed=True, selection=selection)
    data = R._scan_data(scan, selection, "scan")
    cfg = R.RegisterConfig(stage1_iterations=20, stage1_shape_iterations=0, surface_rounds=0, iterations=0)
    st1 = R.fit_landmarks(model, torch.as_tensor(data.landmarks[None]), selection, cfg)
    st1 = dataclasses.replace(st1, shape_offsets=None)
    init = 0.01 * torch.randn(1, model.num_vertices, 3, generator=gen, dtype=model.template.dtype)
    v_d, s_hat, _ = R.refine(model, [data], st1, selection, cfg, init=init)
    torch.testing.assert_close(v_d, init)
    with torch.no_grad():
        again = pose(model, model.template + init[0], bone_scales=st1.bone_scales, angles=st1.angles,
                     global_orient=st1.global_orient, transl=st1.transl).vertices
    torch.testing.assert_close(s_hat, again, atol=1e-5, rtol=0)
    energy = R.Stage2Energy(model, [data], st1, selection, cfg)
    torch.testing.assert_close(energy.displacement(energy.mesh(init)), init, atol=1e-5, rtol=0)
    at_stage1 = energy.terms(energy.s_t, energy.pairs(energy.s_t, np.random.default_rng(0)))
    assert float(at_stage1["ev"]) == 0.0 and float(at_stage1["rigid"]) == 0.0  # S^ = S^_T
    moved = energy.terms(s_hat, energy.pairs(s_hat, np.random.default_rng(0)))
    assert float(moved["ev"]) > 0 and float(energy.total(moved)) > cfg.lambda_ev * float(moved["ev"])
    # "sum" normalisation: the same terms times their element counts, over V
    summed = R.Stage2Energy(model, [data], st1, selection, dataclasses.replace(cfg, normalisation="sum"))
    pairs = energy.pairs(s_hat, np.random.default_rng(1))
    m, s = energy.terms(s_hat, pairs), summed.terms(s_hat, pairs)
    nv = model.num_vertices
    torch.testing.assert_close(s["mnn"], m["mnn"] * m["pairs"].to(m["mnn"].dtype) / nv)
    torch.testing.assert_close(s["ev"], m["ev"] * energy.edges.shape[0] / nv)
    torch.testing.assert_close(s["lm"], m["lm"] * energy.lm_count / nv)
    torch.testing.assert_close(s["smooth"], m["smooth"])


def test_sample_surface_on_triangle():
    rng = np.random.default_rng(0)
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 0]], float)
    f = np.array([[0, 1, 2], [1, 3, 2]])
    fi, w = R.sample_surface(v, f, 4000, rng)
    assert np.allclose(w.sum(1), 1) and (w >= 0).all()
    area = np.array([0.5, 0.5 * np.linalg.norm(np.cross(v[3] - v[1], v[2] - v[1]))])
    assert abs((fi == 0).mean() - area[0] / area.sum()) < 0.03


# ------------------------------------------------------------------------------------------------
# Stage 2 and the driver

FAST = dict(stage1_iterations=150, iterations=60, scan_samples=20_000, model_samples=8_000, mnn_refresh=5)


@pytest.mark.parametrize("tangent_weight", [1.0, 0.0])
def test_register_reduces_error(model, gen, selection, tangent_weight):
    scan = synthetic_scan(model, gen, posed=False, selection=selection)
    cfg = R.load_config(R.DEFAULT_CONFIG)
    cfg = R.RegisterConfig(**{**cfg.__dict__, **FAST, "mnn_tangent_weight": tangent_weight})
    reg = R.register(model, [scan], cfg, selection=selection, progress=False)[0]
    m = reg.meta
    mean_mm, max_mm = R.correspondence_error(reg, scan.gt_points)
    assert mean_mm == pytest.approx(m["error_mean_mm"])
    assert mean_mm < 0.85 * m["stage1_error_mean_mm"]
    assert mean_mm < 7.0
    assert reg.vertices.shape == (model.num_vertices, 3) and reg.displacement.shape == (model.num_vertices, 3)
    # S^ = LBS(V_T + V_D, T(b, theta)) (Eq. 5.14's parametrisation).
    with torch.no_grad():
        again = pose(model, model.template + torch.as_tensor(reg.displacement), bone_scales=torch.as_tensor(reg.bone_scales)[None],
                     angles=torch.as_tensor(reg.angles)[None], global_orient=torch.as_tensor(reg.global_orient)[None],
                     transl=torch.as_tensor(reg.transl)[None]).vertices[0]
    np.testing.assert_allclose(again.numpy(), reg.vertices, atol=1e-5)


def test_registration_round_trip(tmp_path, gen):
    v = np.random.default_rng(0).random((10, 3)).astype(np.float32)
    reg = R.Registration(v, np.ones(20, np.float32), np.zeros(47, np.float32), np.zeros(3, np.float32),
                         np.ones(3, np.float32), v * 0.1, {"scan": "a", "error_mean_mm": 1.5})
    path = R.save_registration(reg, tmp_path / "r.npz")
    back = R.load_registration(path)
    for k in ("vertices", "bone_scales", "angles", "global_orient", "transl", "displacement"):
        np.testing.assert_array_equal(getattr(back, k), getattr(reg, k))
    assert back.meta == reg.meta
    np.savez(tmp_path / "bad.npz", format=np.array("blsm-scan"))
    with pytest.raises(ValueError, match="bad.npz: not a BLSM registration"):
        R.load_registration(tmp_path / "bad.npz")
    with pytest.raises(ValueError, match="shape"):
        R.save_registration(R.Registration(v, np.ones(20), np.zeros(47), np.zeros(3), np.zeros(3), v[:5]), tmp_path / "x.npz")
    with pytest.raises(ValueError, match="gt_points"):
        R.correspondence_error(reg, v[:4])


def test_config_file(tmp_path):
    good = tmp_path / "c.yaml"
    good.write_text("iterations: 7\nlr: 0.001\n")
    cfg = R.load_config(good)
    assert cfg.iterations == 7 and cfg.lr == 0.001
    bad = tmp_path / "b.yaml"
    bad.write_text("iteratons: 7\n")
    with pytest.raises(ValueError, match="b.yaml: iteratons: unknown key"):
        R.load_config(bad)
    bad.write_text("iterations: many\n")
    with pytest.raises(ValueError, match="expected an integer"):
        R.load_config(bad)
    assert R.load_config(R.DEFAULT_CONFIG).iterations > 0  # the shipped defaults parse
    bad.write_text("shape_init: 1\n")
    with pytest.raises(ValueError, match="expected true or false"):
        R.load_config(bad)


def test_shipped_config_equals_defaults():
    # One source of truth: the YAML `blsm register` reads and RegisterConfig() agree.
    assert R.load_config(R.DEFAULT_CONFIG) == R.RegisterConfig()


def _landmark_yaml(path: Path, names, idx) -> Path:
    path.write_text("".join(f"{n}: {{vertex: {int(i)}}}\n" for n, i in zip(names, idx)))
    return path


def test_cli(tmp_path, model, gen, selection, capsys):
    scan = synthetic_scan(model, gen, posed=True, selection=selection, holes=False)
    vidx = selection.vertices[:, 0].numpy()
    lm = _landmark_yaml(tmp_path / "lm.yaml", scan.landmark_names, vidx)
    cfg = tmp_path / "c.yaml"
    cfg.write_text("stage1_iterations: 20\nstage1_shape_iterations: 5\nsurface_rounds: 1\nsurface_iterations: 2\n"
                   "iterations: 3\nscan_samples: 2000\nmodel_samples: 1000\n")
    good = write_scan_npz(scan, tmp_path / "s1.npz")
    out = tmp_path / "out"
    args = [str(good), "--landmark-definitions", str(lm), "--out", str(out), "--config", str(cfg)]
    assert R.main(args) == 0
    reg = R.load_registration(out / "s1.npz")
    assert reg.meta["scan"] == "posed" and reg.meta["iterations"] == 3
    capsys.readouterr()
    assert R.main(args) == 2  # never overwrites silently
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists" in err[0]

    bad_v = scan.vertices.copy()
    bad_v[3] = np.nan
    cases = {
        "nan.npz": dict(vertices=bad_v),
        "empty.npz": dict(vertices=np.zeros((0, 3), np.float32), faces=np.zeros((0, 3), np.int32)),
        "nonmanifold.npz": dict(faces=np.concatenate([scan.faces, scan.faces[:1], scan.faces[:1]])),
        "nolm.npz": dict(landmarks=np.full_like(scan.landmarks, np.nan)),
    }
    for name, override in cases.items():
        p = write_scan_npz(scan, tmp_path / name, **override)
        assert R.main([str(p), "--landmark-definitions", str(lm), "--out", str(out), "--config", str(cfg)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and name in err[0], (name, err)
    # A user's mesh with its located landmarks in a JSON file (--landmarks), e.g. from a scanner.
    import json

    import trimesh

    mesh = tmp_path / "user_scan.obj"
    trimesh.Trimesh(scan.vertices, scan.faces, process=False).export(mesh)
    lm_json = tmp_path / "user_scan_landmarks.json"
    lm_json.write_text(json.dumps({n: [float(c) for c in x] for n, x in zip(scan.landmark_names, scan.landmarks)}))
    assert R.main([str(mesh), "--landmarks", str(lm_json), "--out", str(out), "--config", str(cfg)]) == 0
    assert R.load_registration(out / "user_scan.npz").vertices.shape == (model.num_vertices, 3)
    assert R.main([str(mesh), str(good), "--landmarks", str(lm_json), "--out", str(tmp_path / "o2")]) == 2
    assert "one scan" in capsys.readouterr().err
    assert R.main([str(mesh), "--out", str(tmp_path / "o3"), "--config", str(cfg)]) == 2  # no landmarks
    assert "user_scan" in capsys.readouterr().err
    (tmp_path / "junk.npz").write_text("not a zip")
    assert R.main([str(tmp_path / "junk.npz"), "--landmark-definitions", str(lm), "--out", str(out)]) == 2
    assert "junk.npz" in capsys.readouterr().err


def test_population_scan_registers(model, selection, tmp_path):
    """A real Anny population scan (noise, holes, 5 mm landmark noise) against its ground truth."""
    pytest.importorskip("anny")
    from blsm.learn.population import make_population, read_population
    from blsm.learn.scans import load_scan

    # The population is made with the packaged rig (its template defines the ground truth).
    make_population(out=tmp_path / "pop", n_subjects=1, posed_subjects=1, poses_per_subject=1, seed=3,
                    test_fraction=0.0)
    index = read_population(tmp_path / "pop")
    scan = load_scan(tmp_path / "pop" / index["subjects"][0]["scans"][1])  # the posed scan
    reg = R.register(model, [scan], R.RegisterConfig(), selection=selection, progress=False)[0]
    m = reg.meta
    # Measured 4.4-5.4 mm mean on such scans (the thesis-only pipeline: 5-6 mm); the target of
    # 3 mm is not reached (see the module docstring).
    assert m["error_mean_mm"] < 6.5
    assert m["error_mean_mm"] < m["stage1_error_mean_mm"]
    # The shape-space landmark fit beats the skeleton-only floor (about 12 mm on Anny bodies).
    assert m["surface_fit_landmark_rms_mm"] < 11.0
