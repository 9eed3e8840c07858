"""recovery.models.mesh_ae (Table 4.1) and recovery.mesh.operators (cache, keypoint regressor)."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest
import torch
from recovery_helpers import sphere

from blsm.spiral.hierarchy import MeshOpsSettings, mesh_hierarchy
from blsm.spiral.sampling import Level
from recovery.mesh.operators import mesh_operators
from recovery.models.mesh_ae import MeshAutoencoder

SMALL = MeshOpsSettings(factors=(4, 2), rings=(2, 1), lengths=(19, 7))


@pytest.fixture(scope="module")
def small_ops():
    v, f = sphere(3)
    return mesh_hierarchy(v, f, SMALL)


def relabelled(ops, perm: np.ndarray):
    """The same operators on the template with vertex i := old vertex perm[i] (level 0 only changes)."""
    inv = np.argsort(perm)
    s0 = ops.spirals[0][perm]
    s0 = np.where(s0 >= 0, inv[np.maximum(s0, 0)], -1)
    lv = ops.levels[0]
    first = Level(down=inv[lv.down], up_index=lv.up_index[perm], up_weight=lv.up_weight[perm], faces=lv.faces)
    return dataclasses.replace(ops, spirals=[s0, *ops.spirals[1:]], levels=[first, *ops.levels[1:]],
                               faces=[inv[ops.faces[0]], *ops.faces[1:]], reference=ops.reference[perm])


def test_relabelling_the_template_relabels_the_output(small_ops):
    torch.manual_seed(0)
    nv = len(small_ops.reference)
    mean, std = torch.randn(nv, 3) * 0.1, torch.rand(nv, 3) + 0.5
    ae = MeshAutoencoder(small_ops, mean, std, channels=(8, 16), latent=16)
    perm = np.random.default_rng(1).permutation(nv)
    ops2 = relabelled(small_ops, perm)
    ae2 = MeshAutoencoder(ops2, mean[perm], std[perm], channels=(8, 16), latent=16)
    # the same weights: only buffers differ (permuted operators)
    ae2.load_state_dict({k: v for k, v in ae.state_dict().items() if "indices" not in k and "down" not in k
                         and "up_" not in k and "normalizer" not in k}, strict=False)
    v = torch.randn(3, nv, 3)
    out = ae.reconstruct(v)
    out2 = ae2.reconstruct(v[:, perm])
    torch.testing.assert_close(out2, out[:, perm], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(ae2.encoder(ae2.normalizer(v[:, perm])), ae.encoder(ae.normalizer(v)), rtol=1e-5, atol=1e-5)


def test_table_4_1_shapes(small_ops):
    ae = MeshAutoencoder(small_ops, torch.zeros(642, 3), torch.ones(642, 3), channels=(16, 32), latent=128)
    sizes = small_ops.sizes
    assert ae.encoder.conv_in.indices.shape == (sizes[0], 19)
    assert ae.encoder.fc.in_features == sizes[-1] * 32 and ae.encoder.fc.out_features == 128
    assert ae.decoder.conv_out.linear.out_features == 3
    z = ae.encoder(torch.zeros(2, 642, 3))
    assert z.shape == (2, 128) and ae.decoder(z).shape == (2, 642, 3)


def test_autoencoder_overfits_a_handful_of_meshes(small_ops):
    torch.manual_seed(0)
    v0 = torch.as_tensor(small_ops.reference, dtype=torch.float32)
    meshes = torch.stack([v0 * torch.tensor([1 + 0.2 * k, 1.0, 1 - 0.1 * k]) + 0.05 * torch.sin(3 * v0 + k) for k in range(4)])
    ae = MeshAutoencoder(small_ops, meshes.mean(0), meshes.std(0), channels=(8, 16), latent=8)
    opt = torch.optim.Adam(ae.parameters(), lr=3e-3)
    x = ae.normalizer(meshes)
    first = None
    for _ in range(300):
        loss = (ae(x) - x).abs().mean()
        first = float(loss.detach()) if first is None else first
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        err = float((ae.reconstruct(meshes) - meshes).norm(dim=-1).mean())
    spread = float((meshes - meshes.mean(0)).norm(dim=-1).mean())  # the error of predicting the mean mesh
    assert float(loss.detach()) < 0.1 * first
    assert err < 0.1 * spread  # 300 steps: about 0.065


def test_operator_cache_is_keyed_by_the_model_file(tmp_path, model):
    from blsm.model import DEFAULT_MODEL

    settings = MeshOpsSettings(regressor_samples=24, regressor_support=32)
    a = tmp_path / "a.npz"
    shutil.copy(DEFAULT_MODEL, a)
    logs: list[str] = []
    ops = mesh_operators(a, tmp_path / "cache", settings, log=logs.append)
    assert len(logs) == 1 and len(list((tmp_path / "cache").glob("mesh_ops-*.npz"))) == 1
    assert ops.sizes[0] == model.num_vertices and len(ops.sizes) == 5
    again = mesh_operators(a, tmp_path / "cache", settings, log=logs.append)
    assert len(logs) == 1  # read back, not rebuilt
    np.testing.assert_array_equal(again.spirals[0], ops.spirals[0])
    np.testing.assert_array_equal(again.levels[2].up_index, ops.levels[2].up_index)
    # another model file (other bytes) gets its own operators
    with np.load(a) as z:
        arrays = dict(z)
    arrays["template"] = arrays["template"] + np.float32(1e-4)
    np.savez(tmp_path / "b.npz", **arrays)
    mesh_operators(tmp_path / "b.npz", tmp_path / "cache", settings, log=logs.append)
    assert len(logs) == 2 and len(list((tmp_path / "cache").glob("mesh_ops-*.npz"))) == 2
    # the keypoint regressor: surface keypoints copied, joints sum to one
    reg = ops.regressor
    np.testing.assert_allclose(reg.sum(1), 1.0, atol=1e-4)
    assert (reg >= 0).all()
    with torch.no_grad():
        out = model(pose=torch.zeros(1, model.num_dofs))
    kp = reg @ out.vertices[0].numpy()
    surf = model.keypoint_joint.numpy() < 0
    np.testing.assert_allclose(kp[surf], out.keypoints[0].numpy()[surf], atol=1e-5)
    assert np.linalg.norm(kp[~surf] - out.keypoints[0].numpy()[~surf], axis=1).mean() < 0.02


def test_operator_cache_key_does_not_depend_on_number_types():
    """A checkpoint's config gives factors as floats (4.0), YAML as ints (4): the same operators, one cache."""
    from recovery.mesh.operators import _key

    a = MeshOpsSettings(factors=(4, 2, 2, 2), rings=(2, 1, 1, 1), lengths=(25, 9, 9, 9))
    b = MeshOpsSettings(factors=(4.0, 2.0, 2.0, 2.0), rings=(2.0, 1, 1, 1), lengths=(25, 9, 9, 9.0))
    assert a == b and _key("0" * 64, a) == _key("0" * 64, b)
    assert _key("0" * 64, a) != _key("0" * 64, MeshOpsSettings(factors=(4, 2, 2, 3)))
