"""Plausible people and poses by default: the Anny population's ages, prior re-draws, age-matched clips."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import blsm
from blsm.mocap.library import MotionClip, save_clip
from blsm.mocap.plausible import PoseChecker
from synth.config import GeneratorConfig
from synth.poses import PoseSource
from synth.subjects import Population, sample_phenotype


def test_anny_population_draws_exactly_as_anny_did():
    # Population.ANNY (age: [0, 90], children: 0) is the generator before these keys: the same
    # phenotype for the same seed as Anny's own SimpleShapeDistribution.
    from anny.shape_distribution import SimpleShapeDistribution

    from synth.subjects import _anny

    anny_default = SimpleShapeDistribution(_anny())
    for seed in range(3):
        ours = sample_phenotype(np.random.default_rng(seed), Population.ANNY)
        rng = np.random.default_rng(seed)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(rng.integers(2**62)))
            years, ph = anny_default.sample(1)
        assert ours["age_years"] == float(years[0])
        assert all(ours[k] == float(v.reshape(-1)[0]) for k, v in ph.items())


def test_default_population_holds_adults_and_some_children_but_no_infant():
    ages = np.array([sample_phenotype(np.random.default_rng(i))["age_years"] for i in range(400)])
    assert ages.min() >= 5.0 and ages.max() <= 80.0
    children = ages < 18.0
    assert 0.05 < children.mean() < 0.16  # 10 % expected; binomial sd 1.5 %
    assert ages[children].min() >= 5.0 and ages[~children].min() >= 18.0
    only_adults = Population(children=0.0)
    assert min(sample_phenotype(np.random.default_rng(i), only_adults)["age_years"] for i in range(50)) >= 18.0


def _source(**poses) -> PoseSource:
    cfg = GeneratorConfig()
    return PoseSource(cfg.__class__(**{**cfg.__dict__, "poses": cfg.poses.__class__(**{**cfg.poses.__dict__, **poses})}))


def test_prior_draws_are_plausible_by_default_and_as_drawn_when_off():
    checker = PoseChecker(blsm.load())
    on, off = _source(), _source(plausible=False)
    rng_on, rng_off, rng_ref = (np.random.default_rng(5) for _ in range(3))
    redraws = 0
    for _ in range(200):
        x, orient, motion = on.sample(rng_on)
        assert checker.check(torch.from_numpy(x)[None]).plausible[0]
        assert motion["source"] == "prior" and not orient.any()
        redraws += motion["redraws"]
        # Off: exactly the draws the generator made before the option (one seed per draw).
        x_off, _, m_off = off.sample(rng_off)
        g = torch.Generator().manual_seed(int(rng_ref.integers(2**62)))
        np.testing.assert_array_equal(x_off, off.prior.sample(1, g)[0].numpy().astype(np.float32))
        assert "redraws" not in m_off
    assert redraws > 0  # some of 200 draws hit an arm through the torso (about 2.6 % of draws)


def test_a_prior_of_only_implausible_poses_is_a_one_line_error(monkeypatch):
    src = _source(max_redraws=3)
    monkeypatch.setattr(src.checker, "check", lambda x: type("R", (), {"plausible": np.array([False])})())
    with pytest.raises(ValueError, match=r"no plausible pose in 4 draws .*poses.plausible: false"):
        src.sample(np.random.default_rng(0))


def test_children_take_frames_of_the_child_clips_only(tmp_path):
    model = blsm.load()
    for name in ("walk", "dance", "basketball"):
        t = 5
        save_clip(
            MotionClip(
                name=name, fps=30.0, pose=np.zeros((t, model.num_dofs)), global_orient=np.zeros((t, 3)),
                transl=np.zeros((t, 3)), dir_err_mean_deg=np.zeros(t), dir_err_max_deg=np.zeros(t),
                mpjpe_mm=np.zeros(t), segment_err_deg=np.zeros((t, 0)),
                meta={"dof_names": list(model.dof_names), "segments": []},
            ),
            tmp_path / f"{name}.npz",
        )  # fmt: skip
    src = _source(source="library", library=str(tmp_path), child_clips=("walk", "dance"))
    rng = np.random.default_rng(0)
    child = {src.sample(rng, child=True)[2]["clip"] for _ in range(40)}
    adult = {src.sample(rng, child=False)[2]["clip"] for _ in range(40)}
    assert child == {"walk", "dance"} and adult == {"walk", "dance", "basketball"}
    with pytest.raises(ValueError, match="child_clips names 'walk', which clips/exclude_clips leave out"):
        _source(source="library", library=str(tmp_path), exclude_clips=("walk",), child_clips=("walk",))
