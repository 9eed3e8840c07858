"""recovery.tasks.mesh_task: the BEGAN k_t update (Eq. 4.12) by hand, and inside a training step."""

from __future__ import annotations

import pytest
import torch
from recovery_helpers import CROP

from recovery.tasks.mesh_task import began_convergence, began_k_update


def test_k_update_follows_eq_4_12_step_by_step():
    lam, gamma = 1e-3, 0.7
    k = 0.0  # k_0
    k = began_k_update(k, l_real=0.5, l_fake=0.2, lambda_k=lam, gamma=gamma)
    assert k == pytest.approx(1e-3 * (0.35 - 0.2))  # 1.5e-4
    k = began_k_update(k, l_real=0.4, l_fake=0.1, lambda_k=lam, gamma=gamma)
    assert k == pytest.approx(1.5e-4 + 1e-3 * (0.28 - 0.1))  # 3.3e-4
    k = began_k_update(k, l_real=0.1, l_fake=0.5, lambda_k=lam, gamma=gamma)
    assert k == 0.0  # 3.3e-4 - 4.3e-4 < 0: clipped to [0, 1] as BEGAN does
    assert began_k_update(0.9995, 1.0, 0.0, lam, gamma) == 1.0
    assert began_convergence(0.5, 0.2, gamma) == pytest.approx(0.5 + 0.15)


def test_a_began_training_step(cache_dir, model, tmp_path):
    """One step of the image-to-mesh network with the BEGAN discriminator: k moves by Eq. 4.12 with
    the step's logged L_AE values, and the discriminator's weights change."""
    from blsm.spiral.hierarchy import MeshOpsSettings
    from recovery.config import (
        BeganConfig,
        DataConfig,
        LossConfig,
        MeshConfig,
        ModelConfig,
        OptimConfig,
        RecoveryConfig,
        TrainConfig,
    )
    from recovery.datasets.augment import BatchAugment
    from recovery.datasets.cache import CropCache
    from recovery.mesh.operators import mesh_operators
    from recovery.tasks.mesh_task import MeshTask

    settings = MeshOpsSettings(regressor_samples=24, regressor_support=32)
    ops = mesh_operators(None, tmp_path / "ops", settings, log=lambda *a: None)
    cfg = RecoveryConfig(
        task="mesh",
        model=ModelConfig(backbone="resnet18", pretrained=False),
        data=DataConfig(train=(str(cache_dir),), crop=CROP, augment=None),
        loss=LossConfig(vertices=1.0, keypoints_2d=1.0, keypoints_3d=0.0),
        mesh=MeshConfig(channels=(4, 4, 4, 4), latent=8, hidden=32),
        began=BeganConfig(enabled=True, k0=0.5, lambda_k=0.1),
        optim=OptimConfig(lr=1e-3, warmup_steps=0),
        train=TrainConfig(steps=4, batch_size=4, device="cpu"),
    )
    cache = CropCache([cache_dir])
    nv = model.num_vertices
    task = MeshTask(cfg, model, ops, torch.zeros(nv, 3), torch.ones(nv, 3) * 0.1, torch.tensor([0.5, 0.0, 0.0]),
                    cache.keypoint_names, {})
    batch = BatchAugment(CROP, cache.context, None, 0, model.dof_mirror, cache.keypoint_names)([cache[i] for i in range(4)])
    before = [p.detach().clone() for p in task.disc.parameters()]
    logs = task.training_step(batch, 0)
    assert logs["k"] == 0.5  # logged before the update
    want = began_k_update(0.5, logs["d_real"], logs["d_fake"], 0.1, 0.7)
    assert task.k == pytest.approx(want)
    assert logs["adv"] == pytest.approx(logs["d_fake"], rel=1e-4)  # L_Gadv = L_AE(fake), Eq. 4.11
    assert any(not torch.equal(a, b) for a, b in zip(before, task.disc.parameters()))
    assert all(torch.isfinite(torch.tensor(v)) for v in logs.values())
