"""recovery.tasks.hmr_task: HMR-BLSM's training step can fit a batch, and stops on a non-finite loss."""

from __future__ import annotations

import pytest
import torch
from recovery_helpers import CROP, one_thread

from recovery.config import (
    DataConfig,
    DiscriminatorConfig,
    LossConfig,
    ModelConfig,
    OptimConfig,
    RecoveryConfig,
    TrainConfig,
    load_config,
)
from recovery.datasets.augment import BatchAugment
from recovery.datasets.cache import CropCache
from recovery.eval import metrics as M
from recovery.eval.joints import indices
from recovery.models.heads import ParamLayout
from recovery.models.hmr import predict_body
from recovery.tasks.hmr_task import HMRTask, theta0
from recovery.utils.schedule import warmup_cosine

# The smallest budget that fits the 8 crops to a few millimetres for several seeds (2.5-3.3 mm mean,
# 7.4 mm worst crop over seeds 0-3; 40 steps leave 7-12 mm, 50 steps 4-5 mm).
STEPS = 60


@pytest.fixture(scope="module")
def fit(cache_dir, model):
    """A ResNet-18 trained for STEPS steps on the first 8 cache crops (no augmentation, dropout or
    discriminator), with the PA-MPJPE of those crops (mm) before and after."""
    cache = CropCache([cache_dir])
    cfg = RecoveryConfig(
        model=ModelConfig(backbone="resnet18", pretrained=False, hidden=256, dropout=0.0),
        data=DataConfig(train=(str(cache_dir),), crop=CROP, augment=None),
        # 3D keypoints and the angles themselves (through Eq. 6's tanh alone a joint can saturate at
        # the wrong end of its range and stay there).
        loss=LossConfig(
            keypoints_2d=0.1,
            keypoints_3d=1.0,
            pose=1.0,
            global_orient=0.1,
            bone=0.01,
            shape=0.0,
            adversarial=0.0,
        ),
        discriminator=DiscriminatorConfig(enabled=False),
        optim=OptimConfig(lr=2e-3, weight_decay=0.0, schedule="cosine", warmup_steps=0, grad_clip=0.0),
        train=TrainConfig(steps=STEPS, batch_size=8, device="cpu"),
    )
    torch.manual_seed(0)
    layout = ParamLayout(model.num_dofs, model.num_bone_coeffs, cfg.model.num_shape)
    task = HMRTask(cfg, model, theta0(cache, layout, CROP), None, cache.keypoint_names, {})
    batch = BatchAugment(CROP, cache.context, None, 0, model.dof_mirror, cache.keypoint_names)(
        [cache[i] for i in range(8)]
    )
    ev = torch.tensor(indices(model.keypoint_names))

    @torch.no_grad()
    def pa_mpjpe_mm() -> torch.Tensor:
        # In training mode (batch statistics, no dropout): at 32 px ResNet-18's last stage is 1 x 1,
        # where BatchNorm's running variance (unbiased, over 8 values) is not the batch's.
        task.model.train()
        out = predict_body(model, task.model(batch["image"]), batch["K_crop"], CROP)
        return M.pa_mpjpe(out.keypoints_3d[:, ev], batch["keypoints_3d"][:, ev]) * 1000

    with one_thread():  # module fixtures start before the per-test one-thread fixture
        before = pa_mpjpe_mm()
        logs = [task.training_step(batch, s) for s in range(STEPS)]
        return task, batch, before, pa_mpjpe_mm(), logs


def test_overfits_eight_crops_to_under_10_mm(fit):
    _, _, before, after, logs = fit
    assert before.mean() > 50.0  # Theta_0 is far from these people
    assert after.mean() < 10.0, after
    assert logs[-1]["kp3d"] < 0.1 * logs[0]["kp3d"]
    assert logs[-1]["lr"] == pytest.approx(0.0, abs=1e-9)  # the cosine schedule ran to its end
    assert set(logs[0]) == {"kp2d", "kp3d", "pose", "orient", "bone", "total", "lr"}


def test_non_finite_loss_stops_with_the_step_and_the_samples(fit):
    task, batch, *_ = fit
    bad = dict(batch, keypoints_3d=batch["keypoints_3d"].clone())
    bad["keypoints_3d"][2, 5, 0] = float("nan")
    keys = batch["key"].tolist()
    before = [p.detach().clone() for p in task.model.regressor.parameters()]
    with pytest.raises(
        FloatingPointError, match=r"non-finite loss kp3d, total at step 99; batch samples"
    ) as err:
        task.training_step(bad, 99)
    assert str(keys[2]) in str(err.value)
    assert all(torch.equal(a, b) for a, b in zip(before, task.model.regressor.parameters(), strict=True))


def test_warmup_then_cosine():
    assert warmup_cosine(0, 100, 10, "cosine") == pytest.approx(0.1)
    assert warmup_cosine(9, 100, 10, "cosine") == pytest.approx(1.0)
    assert warmup_cosine(10, 100, 10, "cosine") == pytest.approx(1.0)
    assert warmup_cosine(55, 100, 10, "cosine") == pytest.approx(0.5)
    assert warmup_cosine(100, 100, 10, "cosine") == pytest.approx(0.0)
    assert warmup_cosine(70, 100, 10, "constant") == 1.0


def test_init_backbone_rate_and_frozen_batchnorm(run_a, cache_dir, model):
    """train.init starts from a checkpoint's weights; optim.backbone_lr scales the backbone's rate;
    train.frozen_bn keeps the backbone's BatchNorm statistics through a training step."""
    import dataclasses

    from recovery.predictor import load_predictor
    from recovery.train import preflight

    base = load_config(run_a.parent / "config.yaml")
    cfg = dataclasses.replace(base, optim=dataclasses.replace(base.optim, backbone_lr=0.1),
                              discriminator=dataclasses.replace(base.discriminator, enabled=False),
                              train=dataclasses.replace(base.train, init=str(run_a / "best.pt"), frozen_bn=True))
    cache = CropCache([cache_dir])
    layout = ParamLayout(model.num_dofs, model.num_bone_coeffs, cfg.model.num_shape)
    task = HMRTask(cfg, model, theta0(cache, layout, CROP), None, cache.keypoint_names, {})
    task.model.load_state_dict(preflight(cfg))  # what recovery train does after the task's setup
    src = load_predictor(run_a / "best.pt", log=lambda *a: None).model.state_dict()
    for k, v in task.model.state_dict().items():
        assert torch.equal(v, src[k].to(v.dtype)), k
    lrs = [g["lr"] for g in task.opt.param_groups]
    assert lrs[1] == pytest.approx(0.1 * lrs[0])
    bn = [m for m in task.model.backbone.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]
    before = [m.running_mean.clone() for m in bn]
    aug = BatchAugment(CROP, cache.context, None, 0, model.dof_mirror, cache.keypoint_names)
    with one_thread():
        task.training_step(aug([cache[(0, i)] for i in range(4)]), 0)
    assert all(torch.equal(a, m.running_mean) for a, m in zip(before, bn, strict=True))
    # a checkpoint of another network, or of another task, is refused before anything is built;
    # a resumed run does not read it (its last.pt holds every weight)
    other = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, hidden=32))
    with pytest.raises(ValueError, match="not a checkpoint of this network"):
        preflight(other)
    mesh = dataclasses.replace(cfg, task="mesh", discriminator=type(cfg.discriminator)(),
                               model=type(cfg.model)(backbone=cfg.model.backbone, pretrained=False),
                               optim=dataclasses.replace(cfg.optim, backbone_lr=1.0),
                               train=dataclasses.replace(cfg.train, frozen_bn=False))
    with pytest.raises(ValueError, match="not a checkpoint of this network"):
        preflight(mesh)
    assert preflight(other, resume=True) is None
