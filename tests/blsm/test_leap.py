"""blsm.leap: LEAP's equations on BLSM bodies (Eqs. 10-13), the shape encoder's inversion of the
model and the networks' shapes."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from blsm.leap import Leap, LeapConfig, blend_forward, blend_inverse


@pytest.fixture(scope="module")
def bodies(model):
    g = torch.Generator().manual_seed(0)
    n = 3
    bone = model.population_bone[:n]
    with torch.no_grad():
        out = model(pose=torch.randn(n, model.num_dofs, generator=g), bone=bone,
                    global_orient=0.3 * torch.randn(n, 3, generator=g), transl=torch.randn(n, 3, generator=g))
    return bone, out


def test_blend_inverse_undoes_lbs(model, bodies):
    """Eq. 10 with the true weights of a template vertex maps its posed position back (Eq. 9)."""
    bone, out = bodies
    B = out.skinning_transforms
    idx = torch.arange(0, model.num_vertices, 97)
    rest = out.template[:, idx]
    w = model.weights[idx][None].expand(len(B), -1, -1)
    n, m = len(B), len(idx)
    Bp = B[:, None].expand(-1, m, -1, -1, -1).reshape(n * m, *B.shape[1:])
    posed = blend_forward(w.reshape(n * m, -1), Bp, rest.reshape(-1, 3))
    assert torch.allclose(posed.reshape(n, m, 3), out.vertices[:, idx], atol=1e-5)
    back = blend_inverse(w.reshape(n * m, -1), Bp, posed)
    assert torch.allclose(back.reshape(n, m, 3), rest, atol=1e-5)


def test_shape_encoder_inverts_the_model(model, bodies):
    """The bones' scales give back the rest joints and the template's bone part (no shape coefficients)."""
    bone, out = bodies
    leap = Leap(model)
    body = leap.body(out.skinning_transforms)
    assert torch.allclose(body["joints"], out.rest_joints, atol=1e-5)
    with torch.no_grad():
        want = model(bone=bone).template[:, leap.sub]
    assert torch.allclose(body["rest"], want, atol=1e-4)
    rot = body["R"]
    assert torch.allclose(rot @ rot.transpose(-1, -2), torch.eye(3).expand_as(rot), atol=1e-5)


@pytest.mark.parametrize("cycle", [True, False])
def test_forward_shapes_and_cycle(model, bodies, cycle):
    _, out = bodies
    leap = Leap(model, LeapConfig(width=32, blocks=1, mesh_points=64, cycle=cycle))
    x = out.vertices[:, :50] + 0.01
    r = leap(out.skinning_transforms, x)
    assert r["logits"].shape == (3, 50) and r["w_inv"].shape == (3, 50, model.num_joints)
    assert torch.allclose(r["w_inv"].sum(-1), torch.ones(3, 50), atol=1e-5)
    if cycle:
        assert (r["d"] >= 0).all() and (r["d"] <= 2.0 + 1e-5).all()
    else:
        assert (r["d"] == 0).all()
    r["logits"].sum().backward()  # differentiable end to end, w.r.t. the networks
    assert leap.onet.inp.weight.grad is not None


def test_data_points_and_splits(model, tmp_path):
    import numpy as np

    from blsm import occupancy
    from blsm.leap.data import body_points, draw_bodies, load_clips, subject_split

    train, unseen = subject_split(len(model.population_bone))
    assert len(np.intersect1d(train, unseen)) == 0 and (unseen % 10 == 9).all() and len(unseen) == len(model.population_bone) // 10
    g = torch.Generator().manual_seed(1)
    np.savez(tmp_path / "clip_a.npz", pose=torch.randn(5, model.num_dofs, generator=g).numpy(), global_orient=np.zeros((5, 3)))
    clips = load_clips(tmp_path)
    rng = np.random.default_rng(0)
    bodies = draw_bodies(model, clips, unseen, 2, rng)
    assert bodies.B.shape == (2, model.num_joints, 3, 4) and set(bodies.subject) <= set(unseen)
    p = body_points(model, bodies.vertices[0], bodies.template[0], 400, rng)
    assert p["x"].shape == (400, 3) and p["w"].shape == (400, model.num_joints)
    want = occupancy.inside(p["x"], bodies.vertices[0], model.faces.numpy())  # the exact winding number
    assert np.array_equal(p["occ"] > 0.5, want) and 0.05 < p["occ"].mean() < 0.95
    assert np.allclose(p["wc"].sum(1), 1.0, atol=1e-5)


def test_training_runs_resumes_and_evaluates(model, tmp_path):
    """A few steps of both stages on a tiny set (3 clips of random poses), resumed, evaluated."""
    import numpy as np

    from blsm.leap.train import LeapTrainConfig, evaluate, train

    g = torch.Generator().manual_seed(2)
    lib = tmp_path / "motions"
    lib.mkdir()
    for k in range(3):
        np.savez(lib / f"clip_{k}.npz", pose=0.5 * torch.randn(4, model.num_dofs, generator=g).numpy(), global_orient=np.zeros((4, 3)))
    cfg = LeapTrainConfig(motions=str(lib), held_out_every=3, train_bodies=4, test_bodies=2, points=128, batch_bodies=2,
                          batch_points=64, lbs_steps=3, occupancy_steps=3, save_every=3,
                          net=LeapConfig(width=32, blocks=1, mesh_points=64))
    out = tmp_path / "run"
    train(dataclasses.replace(cfg, occupancy_steps=0), out, log=lambda m: None)  # stops after stage 1 ...
    with pytest.raises(ValueError, match="another config"):
        train(dataclasses.replace(cfg, occupancy_steps=0, lr=1e-2), out, resume=True, log=lambda m: None)
    with pytest.raises(ValueError, match="already there"):
        train(cfg, out, log=lambda m: None)
    out2 = tmp_path / "run2"
    train(cfg, out2, log=lambda m: None)
    ck = torch.load(out2 / "last.pt", weights_only=False)
    assert ck["step"] == 6
    # A longer stage 2 extends a run; a shorter one, or any other change, is refused.
    train(dataclasses.replace(cfg, occupancy_steps=5), out2, resume=True, log=lambda m: None)
    assert torch.load(out2 / "last.pt", weights_only=False)["step"] == 8
    with pytest.raises(ValueError, match="another config"):
        train(dataclasses.replace(cfg, occupancy_steps=4), out2, resume=True, log=lambda m: None)
    with pytest.raises(ValueError, match="another config"):
        train(dataclasses.replace(cfg, occupancy_steps=6, lr=1e-2), out2, resume=True, log=lambda m: None)
    leap = Leap(model, cfg.net)
    leap.load_state_dict(ck["model"])
    with np.load(out2 / "data.npz") as d:
        data = {k: d[k] for k in d.files}
    assert list(data["held_out_clips"]) == ["clip_2"]
    r = evaluate(leap, data, "unseen_subjects")
    assert all(0.0 <= r[k] <= 100.0 for k in ("iou", "iou_near", "iou_all")) and r["bodies"] == 2
    # The ablation's run takes stage 1 from another (lbs_from), with the old loss kinds and a curve.
    # A data file made before the canonical occupancy was kept is completed, with the same values.
    from blsm.leap.train import make_data

    old = tmp_path / "old" / "data.npz"
    old.parent.mkdir()
    np.savez(old, **{k: v for k, v in data.items() if not k.endswith("_occ_c")})
    again = make_data(model, cfg, old, log=lambda m: None)
    for s in ("train", "unseen_poses", "unseen_subjects"):
        assert np.array_equal(again[f"{s}_occ_c"], data[f"{s}_occ_c"]) and 0 < data[f"{s}_occ_c"].mean() < 1
    with np.load(old) as d:
        assert "train_occ_c" in d.files
    abl = dataclasses.replace(cfg, lbs_from=str(out2 / "last.pt"), occupancy_loss="mse", eval_every=2, canonical_points=16,
                              net=dataclasses.replace(cfg.net, cycle=False))
    with pytest.raises(ValueError, match=r"another stage 1 \(lbs_steps differ\)"):
        train(dataclasses.replace(abl, lbs_steps=5), tmp_path / "run4", log=lambda m: None)
    early = dict(ck, step=1)
    torch.save(early, tmp_path / "early.pt")
    with pytest.raises(ValueError, match="stage 1 is not finished"):
        train(dataclasses.replace(abl, lbs_from=str(tmp_path / "early.pt")), tmp_path / "run5", log=lambda m: None)
    train(abl, tmp_path / "run3", log=lambda m: None)
    ck3 = torch.load(tmp_path / "run3" / "last.pt", weights_only=False)
    assert ck3["step"] == 6 and [h["step"] for h in ck3["history"] if "eval" in h] == [4, 6]
    for k, v in ck3["model"].items():
        if k.split(".")[0] in ("inverse", "forward_lbs", "inv_posed", "fwd_rest"):
            assert torch.equal(v, ck["model"][k]), k
    # The paper's L1 (Sec. 4.3) beside the cross-entropy used by default.
    from blsm.leap.train import _batch, lbs_loss

    b = _batch(data, "unseen_subjects", np.random.default_rng(0), 2, 16)
    body = leap.body(b["B"])
    c_inv, c_fwd = leap.lbs_conditions(body)
    want = (leap.inverse_weights(b["x"], b["B"], c_inv) - b["w"]).abs().sum(-1).mean()
    want = want + (leap.forward_weights(b["xc"], c_fwd) - b["wc"]).abs().sum(-1).mean()
    assert torch.allclose(lbs_loss(leap, b, "l1"), want, atol=1e-6)
    assert lbs_loss(leap, b, "ce") > 0


def test_encode_features():
    from blsm.leap.model import encode

    x = torch.tensor([[0.25, -0.5, 1.0]])
    assert torch.equal(encode(x, 0), x)
    f = encode(x, 2)
    assert f.shape == (1, 15)
    assert torch.allclose(f[0, :3], x[0])
    assert torch.allclose(f[0, 3:9], torch.sin(torch.pi * torch.tensor([0.25, 0.5, -0.5, -1.0, 1.0, 2.0])), atol=1e-6)
    assert torch.allclose(f[0, 9:], torch.cos(torch.pi * torch.tensor([0.25, 0.5, -0.5, -1.0, 1.0, 2.0])), atol=1e-6)


def test_bone_frames_read_each_bones_canonical_point(model, bodies, monkeypatch):
    """With ``bone_frames`` the inverse network is fed ``B_k^-1 x`` for every bone (Eq. 10 with
    one-hot weights): for a template vertex, the frame of a bone that fully owns it gives it back."""
    _, out = bodies
    leap = Leap(model, LeapConfig(width=16, blocks=1, mesh_points=64, fourier=0))
    seen = {}
    monkeypatch.setattr(leap.inverse, "forward", lambda f, c: seen.setdefault("f", f) @ torch.zeros(f.shape[1], model.num_joints))
    v = int((model.weights.max(1).values > 0.999).nonzero()[0])
    k = int(model.weights[v].argmax())
    B = out.skinning_transforms
    c_inv = leap.lbs_conditions(leap.body(B))[0]
    leap.inverse_logits(out.vertices[:, v : v + 1], B, c_inv)
    feats = seen["f"].reshape(len(B), model.num_joints, 3)
    assert torch.allclose(feats[:, k], out.template[:, v], atol=1e-5)


def test_surface_from_occupancy_is_outward_and_close():
    """Marching cubes of an occupancy field: faces outward, Chamfer to the true surface under a
    grid cell (a sphere of radius 0.3 m standing in for a body)."""
    import numpy as np
    import trimesh

    from blsm.leap.mesh import chamfer, reconstruct

    class Ball(torch.nn.Module):
        def forward(self, B, x):
            return {"logits": 200.0 * (0.3 - x.norm(dim=-1))}

    lo, hi = np.full(3, -0.4), np.full(3, 0.4)
    v, f = reconstruct(Ball(), np.zeros((20, 3, 4), np.float32), lo, hi, res=33)
    tri = v[f]
    assert np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6 > 0  # outward
    sphere = trimesh.creation.icosphere(5, radius=0.3)
    cd = chamfer((v, f), (np.asarray(sphere.vertices), np.asarray(sphere.faces)), 5000, np.random.default_rng(0))
    assert cd < 0.8 / 32 / 4
    empty = reconstruct(Ball(), np.zeros((20, 3, 4), np.float32), lo + 1.0, hi + 1.0, res=9)
    assert empty[1].shape == (0, 3) and chamfer(empty, (v, f), 10, np.random.default_rng(0)) == float("inf")


def test_true_meshes_are_the_models(model):
    import numpy as np

    from blsm.leap.data import draw_bodies
    from blsm.leap.mesh import true_meshes

    clips = {"a": (0.5 * np.random.default_rng(3).standard_normal((4, model.num_dofs)).astype(np.float32), np.zeros((4, 3), np.float32))}
    bodies = draw_bodies(model, clips, np.arange(20), 2, np.random.default_rng(4))
    assert np.allclose(true_meshes(model, bodies.B, bodies.subject), bodies.vertices, atol=1e-5)


def test_losses_and_config_checks():
    from blsm.leap.train import LeapTrainConfig

    with pytest.raises(ValueError, match="lbs_loss"):
        LeapTrainConfig(lbs_loss="l2")
    with pytest.raises(ValueError, match="occupancy_loss"):
        LeapTrainConfig(occupancy_loss="hinge")
    with pytest.raises(ValueError, match="eval_every"):
        LeapTrainConfig(eval_every=-1)


@pytest.mark.parametrize("name", ["cpu", "cpu_nocycle", "gpu"])
def test_shipped_configs_parse(name):
    from pathlib import Path

    from blsm.leap.cli import load_config

    cfg = load_config(Path(__file__).resolve().parents[2] / "configs" / "leap" / f"{name}.yaml")
    assert cfg.net.cycle == (name != "cpu_nocycle") and cfg.device == ("cuda" if name == "gpu" else "cpu")
    assert bool(cfg.lbs_from) == (name == "cpu_nocycle")
