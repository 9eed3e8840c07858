"""The packaged pose prior (fitted on the CMU library): limits, and clips it has never seen."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from blsm.joint_limits import angles_from_unconstrained
from blsm.mocap.bvh import read_bvh
from blsm.mocap.prior import X_CLIP, load_prior, uniform_sample
from blsm.mocap.retarget import retarget

PRIOR = Path(__file__).resolve().parents[2] / "blsm" / "data" / "pose_prior_cmu.npz"


def test_packaged_prior_matches_the_model_and_samples_inside_the_limits(model):
    prior = load_prior(PRIOR)
    assert prior.dof_names == model.dof_names
    torch.testing.assert_close(prior.limits.float(), model.dof_limits)
    x = prior.sample(20000, torch.Generator().manual_seed(0))
    ang = angles_from_unconstrained(x.double(), model.dof_limits.double())
    lo, hi = model.dof_limits.double().T
    assert bool(((ang >= lo) & (ang <= hi)).all())
    # The samples are poses from the data, not the rest pose: the knees bend in a fair share.
    knee = ang[:, model.dof_names.index("knee_l.flex")]
    assert 0.1 < float((knee > 0.5).double().mean()) < 0.9


def test_held_out_clips_are_more_likely_than_uniform_poses(model, shared_mocap):
    prior = load_prior(PRIOR)
    held = prior.meta["excluded"]
    assert held and not set(held) & set(prior.meta["clips"])
    gen = torch.Generator().manual_seed(1)
    u = uniform_sample(4000, model.dof_limits.double(), gen).clamp(-X_CLIP, X_CLIP)
    lp_uniform = prior.log_prob(u.to(prior.means.dtype))
    for name in held:
        motion = read_bvh(shared_mocap / f"{name}.bvh", fps=10)
        res = retarget(motion, model, first_iters=150, iters=60)
        x = torch.as_tensor(res.pose).clamp(-X_CLIP, X_CLIP).to(prior.means.dtype)
        lp_clip = prior.log_prob(x)
        assert float(lp_clip.median()) > float(lp_uniform.median()) + 20.0, name
        # Nearly every real frame beats the typical uniform pose.
        assert float((lp_clip > lp_uniform.median()).double().mean()) > 0.95, name
    assert np.isfinite(lp_uniform.numpy()).all()
