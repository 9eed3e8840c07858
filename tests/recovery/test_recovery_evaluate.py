"""recovery.eval.evaluate: ``recovery evaluate`` writes every metric, baseline and split and a results
sheet; the fixed-skeleton baseline is the generalised Procrustes mean."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from recovery_helpers import one_thread

from recovery.cli import main
from recovery.eval import metrics as M
from recovery.eval.evaluate import fixed_skeleton

SEGMENTATION = {"fg_accuracy", "fg_f1", "parts_accuracy", "parts_macro_f1"}


def _similar_copies(gen, base, n, noise=0.0):
    q, _ = torch.linalg.qr(torch.randn(n, 3, 3, generator=gen, dtype=torch.float64))
    q = q * torch.linalg.det(q)[:, None, None]  # proper rotations
    scale = 0.5 + 2 * torch.rand(n, generator=gen, dtype=torch.float64)
    shape = base + noise * torch.randn(n, *base.shape, generator=gen, dtype=torch.float64)
    return scale[:, None, None] * shape @ q.transpose(1, 2) + torch.randn(
        n, 1, 3, generator=gen, dtype=torch.float64
    )


def test_fixed_skeleton_of_similar_skeletons_fits_each_exactly(gen):
    base = torch.randn(17, 3, generator=gen, dtype=torch.float64)
    joints = _similar_copies(gen, base, 6)
    skel = fixed_skeleton(joints)
    assert skel.shape == (17, 3)
    assert M.pa_mpjpe(skel.expand_as(joints), joints).max() < 1e-9
    assert M.pa_mpjpe(skel[None], base[None]).item() < 1e-9


def test_fixed_skeleton_is_the_mean_shape(gen):
    """With each person's shape the base plus noise, the Procrustes mean is nearer the base and
    nearer everyone than any one person is (a constant guess of person 0 would not be)."""
    base = torch.randn(17, 3, generator=gen, dtype=torch.float64)
    joints = _similar_copies(gen, base, 8, noise=0.1)
    skel = fixed_skeleton(joints)
    to_base = M.pa_mpjpe(joints, base.expand_as(joints))
    assert M.pa_mpjpe(skel[None], base[None]).item() < 0.7 * to_base.min()
    each = [M.pa_mpjpe(joints[i].expand_as(joints), joints).mean() for i in range(8)]
    assert M.pa_mpjpe(skel.expand_as(joints), joints).mean() < min(each)


@pytest.fixture(scope="module")
def evaluated(run_a, fake_root, tmp_path_factory):
    out = tmp_path_factory.mktemp("recovery_eval") / "eval"
    with one_thread():
        assert (
            main(["evaluate", str(run_a / "last.pt"), str(fake_root), "--out", str(out), "--batch", "4"]) == 0
        )
    return out, json.loads((out / "metrics.json").read_text())


def test_evaluate_writes_every_metric(evaluated, capsys):
    out, m = evaluated
    for key in ("mpjpe_mm", "pa_mpjpe_mm", "pve_mm", "pck_0.05", "pck_0.1"):
        assert math.isfinite(m[key]) and m[key] >= 0, key
    assert m["people"] == 9 and m["subjects"] == 2 and m["crop"] == 32
    assert 0 <= m["pck_0.05"] <= m["pck_0.1"] <= 1
    assert m["pa_mpjpe_mm"] <= m["mpjpe_mm"]  # the alignment can only help
    assert set(m["segmentation"]) == SEGMENTATION
    assert all(0 <= v <= 1 for v in m["segmentation"].values())
    assert set(m["baselines"]) == {"fixed_skeleton", "mean_pose"}
    for b in m["baselines"].values():
        assert b["pa_mpjpe_mm"] > 0 and b["mpjpe_mm"] > 0
    # Six steps from Theta_0: the network is still about the mean pose.
    assert m["pa_mpjpe_mm"] == pytest.approx(m["baselines"]["mean_pose"]["pa_mpjpe_mm"], rel=0.1)
    assert m["relative"]["pa_mpjpe_vs_fixed_skeleton"] == pytest.approx(
        m["pa_mpjpe_mm"] / m["baselines"]["fixed_skeleton"]["pa_mpjpe_mm"] - 1
    )
    pp = m["pose_prior"]
    assert 0 <= pp["fraction_below"] <= 1 and math.isfinite(pp["threshold_log_prob"])


def test_pose_prior_outliers_counts_implausible_poses():
    from blsm.mocap.prior import load_prior
    from recovery.eval.evaluate import pose_prior_outliers

    prior = load_prior(Path(__file__).parents[2] / "blsm" / "data" / "pose_prior_cmu.npz")
    real = prior.sample(400, torch.Generator().manual_seed(0))
    # Prior draws as predictions: about 1 % fall below the labels' 1st percentile.
    same = pose_prior_outliers(prior.sample(400, torch.Generator().manual_seed(1)), real)
    assert same["fraction_below"] < 0.05 and same["labels_below"] == pytest.approx(0.01, abs=0.005)
    # Every atom at alternating extremes: far outside the mocap distribution.
    odd = torch.tensor([3.0, -3.0] * 23 + [3.0]).expand(10, 47)
    assert pose_prior_outliers(odd, real)["fraction_below"] == 1.0


def test_evaluate_splits(evaluated):
    _, m = evaluated
    s = m["splits"]
    assert set(s) == {"view", "truncated", "people_per_image"}
    # The fake cameras carry no view or truncation: every person counts as normal and whole.
    assert s["view"]["normal"]["people"] == 9 and s["view"]["rare"] == {"people": 0}
    assert s["truncated"]["no"]["people"] == 9 and s["truncated"]["yes"] == {"people": 0}
    assert {k: v["people"] for k, v in s["people_per_image"].items()} == {"1": 2, "2": 7}
    assert s["view"]["normal"]["pa_mpjpe_mm"] == pytest.approx(m["pa_mpjpe_mm"])
    assert set(s["people_per_image"]["2"]["segmentation"]) == SEGMENTATION


def test_evaluate_draws_a_sheet(evaluated):
    from PIL import Image

    out, _ = evaluated
    with Image.open(out / "sheet.png") as im:
        assert im.size[0] == 5 * 128 and im.size[1] > 4 * 128  # 5 columns, rows by quartile
    assert sorted(p.name for p in out.iterdir()) == ["metrics.json", "people.npz", "sheet.png"]


def test_evaluate_keeps_each_persons_errors(evaluated):
    out, m = evaluated
    with np.load(out / "people.npz") as z:
        assert len(z["index"]) == m["people"] and len(set(z["index"].tolist())) == m["people"]
        for k in ("mpjpe_mm", "pa_mpjpe_mm", "pve_mm"):  # the summary is their mean
            assert z[k].shape == (m["people"],) and float(np.nanmean(z[k])) == pytest.approx(m[k])
        assert z["subject"].shape == (m["people"],) and z["pa_mpjpe_mm"].std() > 0


def test_evaluate_max_people(run_a, fake_root, tmp_path):
    assert (
        main(
            ["evaluate", str(run_a / "last.pt"), str(fake_root), "--out", str(tmp_path), "--max-people", "3"]
        )
        == 0
    )
    assert json.loads((tmp_path / "metrics.json").read_text())["people"] == 3


def test_flip_test_is_mirror_equivariant_and_recorded(run_a, fake_root, tmp_path):
    """With ``flip``, the prediction on a mirrored crop is the mirror of the prediction on the crop
    (by construction of the average); without it a trained network is not."""
    from recovery.predictor import load_predictor

    pr = load_predictor(run_a / "last.pt")
    torch.manual_seed(0)
    img = torch.rand(2, 3, pr.crop, pr.crop)
    f = 100.0
    k = torch.tensor([[f, 0.0, pr.crop / 2], [0.0, f, pr.crop / 2], [0.0, 0.0, 1.0]]).expand(2, 3, 3)
    from recovery.models.hmr import unflip_output

    def gap(flip: bool) -> float:
        # Compared in parameters: BLSM itself is not exactly left-right symmetric (its learned
        # skeleton and blendshapes), so mirrored parameters give a mirrored body only to ~1 mm.
        pr.flip = flip
        a, b = pr(img, k).params, unflip_output(pr.body, pr(img.flip(-1), k).params)
        return max(float((getattr(a, n) - getattr(b, n)).abs().max()) for n in ("pose", "orient", "bone", "shape", "cam"))

    assert gap(True) < 1e-4
    assert gap(False) > 1e-3
    assert main(["evaluate", str(run_a / "last.pt"), str(fake_root), "--out", str(tmp_path), "--max-people", "3", "--flip"]) == 0
    assert json.loads((tmp_path / "metrics.json").read_text())["flip_test"] is True
