"""Tests of blsm/learn/evaluation/evaluate.py: held-out errors, tables and plots (thesis Sec. 5.5.2), and ``blsm evaluate``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from blsm.cli import main as blsm_main
from blsm.io import atomic_write
from blsm.learn.evaluation.evaluate import (
    EvalConfig,
    cumulative_auc,
    error_stats,
    evaluate,
    line_plot,
    write_report,
)
from blsm.learn.evaluation.fit import BLSMFittable, FitConfig
from blsm.learn.evaluation.smpl_reimpl import SMPLReimpl, SMPLReimplFittable, ring_regressor
from blsm.learn.registration.registrations import load_registration_set, spread_over_subjects


def main(argv: list[str]) -> int:
    """``blsm evaluate ARGV`` (:mod:`blsm.learn.cli`)."""
    return blsm_main(["evaluate", *argv])


FIT = FitConfig(iterations=(10, 10, 10, 20), lm_iterations=5)


def _write_regs(model, folder, gen, subjects=3, poses=2):
    for s in range(subjects):
        cb = torch.randn(1, model.num_bone_coeffs, generator=gen)
        for p in range(poses):
            angles = torch.zeros(1, model.num_dofs)
            if p:
                angles[0, model.dof_names.index("knee_l.flex")] = 0.4 * p
                angles[0, model.dof_names.index("elbow_r.flex")] = 0.3 * p
            with torch.no_grad():
                v = model(angles=angles, bone=cb).vertices[0].numpy()
            meta = {"subject": f"s{s}", "pose_id": p, "split": "test" if s else "train"}
            with atomic_write(folder / f"s{s}_p{p}.npz") as fh:
                np.savez(fh, vertices=v, meta=np.array(json.dumps(meta)), gt_points=v + 0.001)


@pytest.fixture(scope="module")
def baseline(model):
    reg, _ = ring_regressor(model)
    return SMPLReimpl(model, model.template, model.shape_decoder.basis[:4], reg, {"num_coeffs": 4})


def test_cumulative_auc_matches_numeric_integral(gen):
    e = torch.rand(1000, generator=gen, dtype=torch.float64) * 30.0
    ts = torch.linspace(0, 20, 20001, dtype=torch.float64)
    cdf = (e[None] <= ts[:, None]).double().mean(1)
    assert cumulative_auc(e, 20.0) == pytest.approx(float(torch.trapezoid(cdf, ts)) / 20.0, abs=1e-3)
    assert cumulative_auc(torch.zeros(5)) == 1.0
    assert cumulative_auc(torch.full((5,), 25.0)) == 0.0


def test_error_stats_in_mm():
    s = error_stats(torch.tensor([[0.001, 0.003]]))
    assert s.mean == pytest.approx(2.0) and s.count == 1 and s.sd == pytest.approx(2**0.5)
    with pytest.raises(ValueError):
        error_stats(torch.zeros(0, 3))


def test_evaluate_writes_table_plot_and_json(model, baseline, tmp_path, gen):
    _write_regs(model, tmp_path / "regs", gen)
    regs = load_registration_set(tmp_path / "regs", model.num_vertices)
    assert regs.subjects == ["s0", "s0", "s1", "s1", "s2", "s2"] and regs.pose_ids[:2] == ["0", "1"]
    test = regs.split("test")
    assert len(test.names) == 4
    models = {"BLSM-linear": BLSMFittable(model), "SMPL-reimpl": SMPLReimplFittable(baseline)}
    report = evaluate(models, test, EvalConfig(ks=(1, 3), fit=FIT, batch=4))
    assert set(report.shape["BLSM-linear"]) == {1, 3} and set(report.pose["SMPL-reimpl"]) == {1, 3}
    # bone-only bodies: BLSM with 3 bone coefficients is far better than with 1
    assert report.shape["BLSM-linear"][3].mean < report.shape["BLSM-linear"][1].mean
    assert report.registration is not None
    assert report.registration.mean == pytest.approx(3**0.5, rel=1e-3)  # gt offset by 1 mm per axis
    files = write_report(report, tmp_path / "docs" / "eval.md")
    names = sorted(p.name for p in files)
    assert names == ["eval.json", "eval.md", "eval_pose.png", "eval_shape.png"]
    text = (tmp_path / "docs" / "eval.md").read_text()
    s3 = report.shape["BLSM-linear"][3]
    assert f"{s3.mean:.2f} ± {s3.sd:.2f}" in text and f"{s3.auc:.3f}" in text
    assert "](figures/eval_shape.png)" in text and "Pose generalisation" in text
    data = json.loads((tmp_path / "docs" / "figures" / "eval.json").read_text())
    assert data["shape"]["SMPL-reimpl"]["1"]["mean"] == pytest.approx(report.shape["SMPL-reimpl"][1].mean)
    from PIL import Image

    img = np.asarray(Image.open(tmp_path / "docs" / "figures" / "eval_shape.png"))
    assert img.shape == (480, 720, 3) and (img != 255).any()


def test_main_end_to_end(model, baseline, tmp_path, gen):
    _write_regs(model, tmp_path / "regs", gen, subjects=2)
    baseline.save(tmp_path / "smpl.npz")
    out = tmp_path / "docs" / "blsm_evaluation.md"
    rc = main([
        "--registrations", str(tmp_path / "regs"), "--baseline", str(tmp_path / "smpl.npz"),
        "--out", str(out), "--ks", "2", "--iterations", "10,10,10,20", "--lm-iterations", "2", "--no-pose",
    ])
    assert rc == 0 and out.is_file() and (tmp_path / "docs" / "figures" / "blsm_evaluation_shape.png").is_file()
    assert "| 2 |" in out.read_text()
    assert main(["--registrations", str(tmp_path / "nope"), "--out", str(out)]) == 2


def test_line_plot_draws_series(tmp_path):
    from PIL import Image

    series = {"a": ([1, 2, 4], [3.0, 2.0, 1.0]), "b": ([1, 2, 4], [4.0, 3.5, 3.0])}
    p = line_plot(series, tmp_path / "p.png", "t", "x", "y")
    img = np.asarray(Image.open(p)).astype(int)
    blue = (np.abs(img - np.array([31, 119, 180])).sum(-1) < 10).sum()
    red = (np.abs(img - np.array([214, 39, 40])).sum(-1) < 10).sum()
    assert blue > 100 and red > 100


def test_fitting_the_true_bodies_removes_the_registration_error(model, tmp_path, gen):
    # Bodies of the first 2 bone coefficients (what the test's short fit reaches), registered with
    # 4 mm noise: 6.4 mm mean distance between registration and truth.
    folder = tmp_path / "regs"
    for s in range(2):
        cb = torch.zeros(1, model.num_bone_coeffs)
        cb[0, :2] = torch.randn(2, generator=gen)
        with torch.no_grad():
            v = model(bone=cb).vertices[0].numpy()
        noisy = v + 0.004 * torch.randn(v.shape, generator=gen).numpy()
        meta = {"subject": f"s{s}", "pose_id": 0, "split": "test"}
        with atomic_write(folder / f"s{s}.npz") as fh:
            np.savez(fh, vertices=noisy, meta=np.array(json.dumps(meta)), gt_points=v)
    regs = load_registration_set(folder, model.num_vertices)
    k = 2
    fit = FitConfig(iterations=(20, 20, 20, 40), lm_iterations=20)  # converges on these bodies
    cfg = EvalConfig(ks=(k,), fit=fit, batch=2, pose_generalisation=False)
    on_regs = evaluate({"BLSM": BLSMFittable(model)}, regs, cfg)
    on_gt = evaluate({"BLSM": BLSMFittable(model)}, regs, cfg, targets="ground-truth")
    assert on_gt.info["targets"] == "ground-truth" and on_regs.info["targets"] == "registrations"
    assert on_gt.shape["BLSM"][k].mean < 1.0 and on_regs.shape["BLSM"][k].mean > 5.0
    # The registration error is still reported (the registrations against the truth).
    assert on_gt.registration is not None and on_gt.registration.mean == pytest.approx(on_regs.registration.mean)
    text = write_report(on_gt, tmp_path / "gt.md")[0].read_text()
    assert "true bodies" in text
    regs.gt_points[1] = None
    with pytest.raises(ValueError, match="s1.npz: no ground-truth points"):
        evaluate({"BLSM": BLSMFittable(model)}, regs, cfg, targets="ground-truth")


def test_main_fits_other_models_alongside(model, tmp_path, gen):
    _write_regs(model, tmp_path / "regs", gen, subjects=2)
    from blsm import io
    from blsm.model import DEFAULT_MODEL

    out = tmp_path / "eval.md"
    args = ["--registrations", str(tmp_path / "regs"), "--out", str(out), "--ks", "2",
            "--iterations", "10,10,10,20", "--lm-iterations", "2", "--no-pose", "--targets", "ground-truth"]
    io.save_model(io.read_model(DEFAULT_MODEL), tmp_path / "other.npz")
    assert main([*args, "--also", f"other={tmp_path / 'other.npz'}"]) == 0
    data = json.loads((out.parent / "figures" / "eval.json").read_text())
    assert set(data["shape"]) == {"BLSM-linear", "other"} and data["info"]["targets"] == "ground-truth"
    assert main([*args, "--also", "no-equals-sign"]) == 2


def test_spread_takes_registrations_round_robin_over_subjects(model, tmp_path, gen):
    """The first N registrations in file order can hold a few subjects only; --spread takes every
    subject's first registration before any subject's second."""
    assert spread_over_subjects(["s2", "s2", "s10", "s1", "s1", "s1"], 4) == [0, 2, 3, 4]
    assert spread_over_subjects(["a", "a", "b"], 10) == [0, 1, 2]
    assert spread_over_subjects([], 3) == []
    # sequences: all frames of the first subjects with several, then round-robin over the others
    subjects = ["s1", "s2", "s2", "s2", "s3", "s4", "s4", "s5"]
    assert spread_over_subjects(subjects, 6, sequences=1) == [0, 1, 2, 3, 4, 5]  # s2 whole, s1 s3 s4
    picked = [subjects[i] for i in spread_over_subjects(subjects, 7, sequences=1)]
    assert picked.count("s2") == 3 and picked.count("s4") == 1 and set(picked) == {"s1", "s2", "s3", "s4", "s5"}
    picked = [subjects[i] for i in spread_over_subjects(subjects, 8, sequences=2)]
    assert sorted(picked) == sorted(subjects)
    assert spread_over_subjects(subjects, 2, sequences=1) == [1, 2]  # budget smaller than a sequence
    _write_regs(model, tmp_path / "regs", gen, subjects=3, poses=2)
    base = ["--registrations", str(tmp_path / "regs"), "--split", "all", "--ks", "2", "--iterations",
            "5,5,5,5", "--lm-iterations", "1", "--no-pose", "--max-registrations", "3"]
    for flag, subjects in (([], 2), (["--spread"], 3)):
        out = tmp_path / f"eval{len(flag)}.md"
        assert main([*base, *flag, "--out", str(out)]) == 0
        assert json.loads((out.parent / "figures" / out.with_suffix(".json").name).read_text())["info"]["subjects"] == subjects
