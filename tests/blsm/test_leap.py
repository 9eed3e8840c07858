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
        train(cfg, out, resume=True, log=lambda m: None)
    with pytest.raises(ValueError, match="already there"):
        train(cfg, out, log=lambda m: None)
    out2 = tmp_path / "run2"
    train(cfg, out2, log=lambda m: None)
    ck = torch.load(out2 / "last.pt", weights_only=False)
    assert ck["step"] == 6
    leap = Leap(model, cfg.net)
    leap.load_state_dict(ck["model"])
    with np.load(out2 / "data.npz") as d:
        data = {k: d[k] for k in d.files}
    assert list(data["held_out_clips"]) == ["clip_2"]
    r = evaluate(leap, data, "unseen_subjects")
    assert 0.0 <= r["iou"] <= 100.0 and r["bodies"] == 2
