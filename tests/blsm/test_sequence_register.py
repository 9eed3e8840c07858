"""Tests of the keypoint registration driver (blsm/learn/registration/register.py ``register_keypoints``, thesis
Sec. 6.3), 4D sequences and ``blsm register`` without landmarks (blsm/learn/cli.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from synthetic_scans import subdivide, write_scan_npz

from blsm.cli import main
from blsm.learn.registration.register import KeypointTargets, register_keypoints
from blsm.learn.registration.register_config import RegisterConfig
from blsm.learn.registration.registrations import load_registrations

pytestmark = pytest.mark.usefixtures("one_thread")

TINY_REG = RegisterConfig(iterations=5, scan_samples=2000, model_samples=1000)
TINY_KP = ("rigid_iterations: 10\ntrial_iterations: 0\niterations: 60\nsurface_rounds: 1\n"
           "surface_iterations: 5\nscan_samples: 2000\nmodel_samples: 1000\nstage2_iterations: 0\n")


def _sequence(model, frames: int, selection):
    """``frames`` scans of one subject of the packaged model walking slowly, with landmarks."""
    g = torch.Generator().manual_seed(5)
    x = (torch.randn(1, model.num_dofs, generator=g) * 0.2 + torch.randn(1, model.num_dofs, generator=g) * 0.1
         * torch.linspace(0, 1, frames)[:, None]).to(model.template.dtype)
    tr = torch.zeros(frames, 3, dtype=model.template.dtype)
    tr[:, 2] = torch.linspace(0, 0.1, frames)
    with torch.no_grad():
        out = model(pose=x, bone=model.population_bone[1:2].expand(frames, -1), transl=tr)
    scans = []
    for t in range(frames):
        gt = out.vertices[t].double().numpy()
        v, f = subdivide(gt, model.faces.numpy())
        lms = selection.select(out.vertices[t:t + 1])[0].numpy()
        scans.append(dict(vertices=v.astype(np.float32), faces=f.astype(np.int32), landmarks=lms.astype(np.float32),
                          gt_points=gt.astype(np.float32), meta={"id": f"frame_{t:02d}"}, keypoints=out.keypoints[t]))
    return scans


class _S:
    def __init__(self, d):
        self.__dict__.update(d)


def test_sequence_shares_shape_and_loads(model, selection, tmp_path):
    from blsm.learn.registration.keypoint_fit import load_keypoint_config
    from blsm.learn.registration.registrations import save_registration

    (tmp_path / "k.yaml").write_text(TINY_KP)
    kcfg = load_keypoint_config(tmp_path / "k.yaml")
    scans = [_S(d) for d in _sequence(model, 3, selection)]
    tg = [KeypointTargets(list(model.keypoint_names), s.keypoints.numpy(), np.ones(len(model.keypoint_names)))
          for s in scans]
    regs = register_keypoints(model, scans, tg, TINY_REG, kcfg, sequence=True, progress=False)
    assert len(regs) == 3
    assert regs[0].meta["shape_coeffs"] == regs[2].meta["shape_coeffs"]  # one shape for the subject
    np.testing.assert_array_equal(regs[0].bone_scales, regs[1].bone_scales)
    assert all(r.meta["error_mean_mm"] < 30 for r in regs)
    for r, s in zip(regs, scans):
        save_registration(r, tmp_path / "regs" / f"{s.meta['id']}.npz")
    back = load_registrations([tmp_path / "regs"])  # the format blsm learn reads
    assert len(back) == 3 and back[1].meta["sequence"] is True and back[1].meta["frame"] == 1


def test_stage2_iterations_and_keypoints_in_stage2(model, selection, capsys):
    """``KeypointFitConfig.stage2_iterations`` sets the free-form stage's iterations (0: the
    RegisterConfig's); ``stage2_keypoints`` keeps surface keypoints there as a landmark term and
    refuses joints."""
    import dataclasses

    from blsm.learn.registration.keypoint_fit import KeypointFitConfig, KeypointSet

    kcfg = KeypointFitConfig(rigid_iterations=10, trial_iterations=0, iterations=30, surface_rounds=1,
                             surface_iterations=3, scan_samples=2000, model_samples=1000, stage2_iterations=0)
    scans = [_S(d) for d in _sequence(model, 1, selection)]
    surf = KeypointSet.of_selection(selection)  # surface points, as a learnt A_kp is
    tg = [KeypointTargets(surf.names, scans[0].landmarks, np.ones(len(surf.names)))]
    register_keypoints(model, scans, tg, TINY_REG, kcfg, keypoints=surf)
    assert "stage 2: 5 iterations" in capsys.readouterr().err
    register_keypoints(model, scans, tg, TINY_REG, dataclasses.replace(kcfg, stage2_iterations=7), keypoints=surf,
                       stage2_keypoints=0.5)
    err = capsys.readouterr().err
    assert "stage 2: 7 iterations" in err
    assert "lm rms" in err and "lm rms 0.00 mm" not in err  # the keypoints are in stage 2
    joints = [KeypointTargets(list(model.keypoint_names), scans[0].keypoints.numpy(), np.ones(len(model.keypoint_names)))]
    with pytest.raises(ValueError, match="surface points"):
        register_keypoints(model, scans, joints, TINY_REG, kcfg, stage2_keypoints=0.5, progress=False)


def test_hand_and_foot_search_again_after_some_rounds(model, selection, capsys, monkeypatch):
    """``hand_search_round=k`` splits Eq. 6.5: k rounds, the hands (and with ``foot_search`` the
    feet) searched around that fit, then the remaining rounds; the total stays ``surface_rounds``."""
    import dataclasses

    import blsm.learn.registration.register as reg
    from blsm.learn.registration.keypoint_fit import KeypointFitConfig

    calls = []
    real_hands, real_feet = reg.search_hands, reg.search_feet
    monkeypatch.setattr(reg, "search_hands", lambda *a, **k: calls.append(("hands", k.get("around", False)))
                        or real_hands(*a, **k))
    monkeypatch.setattr(reg, "search_feet", lambda *a, **k: calls.append(("feet", True)) or real_feet(*a, **k))
    kcfg = KeypointFitConfig(rigid_iterations=10, trial_iterations=0, iterations=30, surface_rounds=3,
                             surface_iterations=2, scan_samples=2000, model_samples=1000, stage2_iterations=0)
    scans = [_S(d) for d in _sequence(model, 1, selection)]
    tg = [KeypointTargets(list(model.keypoint_names), scans[0].keypoints.numpy(), np.ones(len(model.keypoint_names)))]
    register_keypoints(model, scans, tg, TINY_REG, kcfg)
    assert calls == [("hands", False)] and capsys.readouterr().err.count("shape round") == 3
    calls.clear()
    register_keypoints(model, scans, tg, TINY_REG, dataclasses.replace(kcfg, hand_search_round=1, foot_search=True))
    assert calls == [("hands", False), ("hands", True), ("feet", True)]
    assert capsys.readouterr().err.count("shape round") == 3


def test_cli_sequence_with_landmarks(model, selection, tmp_path, capsys):
    seq = tmp_path / "seq"
    seq.mkdir()
    for d in _sequence(model, 3, selection):
        write_scan_npz(_SynthLike(d, selection), seq / f"{d['meta']['id']}.npz")
    (tmp_path / "k.yaml").write_text(TINY_KP)
    (tmp_path / "c.yaml").write_text("iterations: 3\nscan_samples: 2000\nmodel_samples: 1000\n")
    out = tmp_path / "out"
    assert main(["register", str(seq), "--sequence", "--out", str(out), "--config", str(tmp_path / "c.yaml"),
                 "--keypoint-config", str(tmp_path / "k.yaml")]) == 0
    regs = load_registrations([out])
    assert [r.meta["frame"] for r in regs] == [0, 1, 2] and regs[0].meta["keypoints_info"]["source"] == "landmarks"
    capsys.readouterr()
    # Bad input: one line naming the file, exit 2.
    (tmp_path / "bad.yaml").write_text("iterationz: 3\n")
    assert main(["register", str(seq), "--sequence", "--out", str(tmp_path / "o2"),
                 "--keypoint-config", str(tmp_path / "bad.yaml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "bad.yaml" in err[0]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["register", str(empty), "--sequence", "--out", str(tmp_path / "o3")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "empty" in err[0] and "no scan files" in err[0]


def test_cli_sequence_frame_spacing_and_outlier_warning(model, selection, tmp_path, capsys):
    """Issue 53: the smoothing follows the frames' spacing in time (the scans' meta, or --fps), and a
    frame whose keypoint error is far above the rest of its sequence is reported in one line with its
    index."""
    seq = tmp_path / "seq"
    seq.mkdir()
    rng = np.random.default_rng(0)
    for k, d in enumerate(_sequence(model, 3, selection)):
        d["meta"].update(pose=k, fps=7.5)  # as blsm.learn.markerless.sequence_scans.make_sequence writes them
        if k == 1:  # keypoints 5 cm off at random: no body fits them
            d["landmarks"] = d["landmarks"] + rng.normal(0, 0.05, d["landmarks"].shape).astype(np.float32)
        write_scan_npz(_SynthLike(d, selection), seq / f"{d['meta']['id']}.npz")
    (tmp_path / "k.yaml").write_text(TINY_KP)
    (tmp_path / "c.yaml").write_text("iterations: 3\nscan_samples: 2000\nmodel_samples: 1000\n")
    args = ["register", str(seq), "--sequence", "--config", str(tmp_path / "c.yaml"),
            "--keypoint-config", str(tmp_path / "k.yaml")]
    assert main([*args, "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err.splitlines()
    assert any("frames 0.1333-0.1333 s apart" in e and "fps 7.5" in e for e in err), err
    warn = [e for e in err if e.startswith("warning:")]
    assert len(warn) == 1 and "median" in warn[0]
    assert warn[0].startswith("warning: frame 1 (frame_01): keypoint rms")
    regs = load_registrations([tmp_path / "out"])
    assert [r.meta["keypoint_outlier"] for r in regs] == [False, True, False]
    assert regs[2].meta["frame_time_s"] == pytest.approx(8 / 30)
    # --fps wins over the scans' meta.
    assert main([*args, "--out", str(tmp_path / "out2"), "--fps", "30"]) == 0
    assert any("frames 0.03333-0.03333 s apart" in e for e in capsys.readouterr().err.splitlines())
    # Bad input: one line, exit 2.
    for bad in (["--fps", "0"], ["--fps", "nan"]):
        assert main([*args, "--out", str(tmp_path / "o3"), *bad]) == 2
        e = capsys.readouterr().err.strip().splitlines()
        assert len(e) == 1 and "--fps" in e[0]
    assert main(["register", str(seq / "frame_00.npz"), "--out", str(tmp_path / "o4"), "--fps", "30"]) == 2
    e = capsys.readouterr().err.strip().splitlines()
    assert len(e) == 1 and "--sequence" in e[0]
    # Frames whose times go back: one line naming the frame, before any fitting.
    back = tmp_path / "back"
    back.mkdir()
    for k, d in enumerate(_sequence(model, 3, selection)):
        d["meta"].update(pose=[0, 2, 1][k], fps=7.5)
        write_scan_npz(_SynthLike(d, selection), back / f"{d['meta']['id']}.npz")
    assert main(["register", str(back), "--sequence", "--out", str(tmp_path / "o5")]) == 2
    e = capsys.readouterr().err.strip().splitlines()
    assert len(e) == 1 and "frame_02" in e[0] and "does not follow" in e[0]


def test_cli_markerless_errors(model, selection, tmp_path, capsys, monkeypatch):
    d = _sequence(model, 1, selection)[0]
    # No landmarks and no colours: nothing to detect keypoints on.
    p = write_scan_npz(_SynthLike(d, selection), tmp_path / "plain.npz",
                       landmarks=np.full((len(selection), 3), np.nan, np.float32))
    assert main(["register", str(p), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "plain.npz" in err[0] and "colours" in err[0]
    # A textured scan where no view finds a person (a detector that never does).
    import blsm.pose2d.detectors as det
    from blsm.learn.markerless.keypoints import mediapipe_points

    monkeypatch.setattr(det, "MediaPipeDetector",
                        lambda *a, **k: det.ProjectedDetector(mediapipe_points(np.zeros((21, 3))), all_missing=True))
    colors = np.full((len(d["vertices"]), 3), 180, np.uint8)
    p = write_scan_npz(_SynthLike(d, selection), tmp_path / "nobody.npz", colors=colors,
                       landmarks=np.full((len(selection), 3), np.nan, np.float32))
    assert main(["register", str(p), "--out", str(tmp_path / "o"), "--views", "3", "--detector", "mediapipe"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nobody.npz" in err[0] and "no person" in err[0]
    assert not (tmp_path / "o").exists() or not list((tmp_path / "o").iterdir())  # nothing half-written


class _SynthLike:
    """What ``write_scan_npz`` needs of a scan."""

    def __init__(self, d, selection):
        self.vertices, self.faces, self.gt_points = d["vertices"], d["faces"], d["gt_points"]
        self.landmark_names, self.landmarks, self.meta = list(selection.names), d["landmarks"], d["meta"]
