"""recovery.checkpoint: checkpoints hold no module path (so moving modules, as issue 33 did, leaves
them readable), and the packaged ``default`` predicts the numbers it predicted when it was packaged."""

from __future__ import annotations

import pickletools
import zipfile
from pathlib import Path

import pytest
import torch
from recovery_helpers import one_thread

from recovery.checkpoint import DEFAULT_CHECKPOINT, read_checkpoint, resolve


def pickled_globals(path: Path) -> set[str]:
    """``module name`` of every global a ``torch.save`` file's pickle names."""
    with zipfile.ZipFile(path) as z:
        data = z.read(next(n for n in z.namelist() if n.endswith("data.pkl")))
    ops = list(pickletools.genops(data))
    found = set()
    for i, (op, arg, _) in enumerate(ops):
        if op.name == "GLOBAL":
            found.add(arg)
        elif op.name == "STACK_GLOBAL":  # module and name are the two strings pushed before it
            found.add(f"{ops[i - 2][1]} {ops[i - 1][1]}")
    return found


def test_default_is_the_packaged_file_in_weights():
    assert resolve("default") == DEFAULT_CHECKPOINT
    assert DEFAULT_CHECKPOINT.parent.name == "weights" and DEFAULT_CHECKPOINT.is_file()


@pytest.mark.parametrize("which", ["default", "run"])
def test_checkpoints_name_no_recovery_module(which, run_a):
    path = DEFAULT_CHECKPOINT if which == "default" else run_a / "last.pt"
    names = pickled_globals(path)
    assert names and not any(n.split()[0].split(".")[0] == "recovery" for n in names), names
    assert read_checkpoint(path)["format"] == "recovery-checkpoint"


# The packaged network's prediction for two fixed random crops, computed when it was packaged
# (recovery.predictor.load_predictor("default") on 2026-12-07, one CPU thread: HMR-BLSM on MoveNet
# Lightning's keypoints, 1600 steps on the full training sets, with its default test-time fit; the
# networks before it were checked the same way).
BEFORE = {  # rounded to 1e-7 (the test allows 1e-4)
    "pose": [[-0.2588201, 0.0440525, 0.0413678, -0.1280626, -0.0310568, -0.0095686],
             [-0.2516247, 0.0508942, 0.0297723, -0.0950194, -0.0202698, -0.0115443]],
    "cam": [[0.88513, 0.0436193, 0.0240454], [0.8921205, 0.0609317, -0.0122346]],
    "transl": [[0.0492802, 0.0271659, 2.2595551], [0.0682998, -0.0137141, 2.2418497]],
    "keypoints_3d": [[[0.0, 0.0, 0.0], [-0.0149032, -0.0311372, -0.0544977], [-0.041976, -0.0217254, -0.1769615]],
                     [[0.0, 0.0, 0.0], [-0.0107598, -0.0392215, -0.051043], [-0.0303184, -0.0471036, -0.1765166]]],
}


def test_packaged_checkpoint_predicts_the_numbers_it_predicted_when_packaged():
    from recovery.predictor import load_predictor

    with one_thread():
        pr = load_predictor("default")
        c = pr.crop
        img = torch.rand(2, 3, c, c, generator=torch.Generator().manual_seed(0))
        k = torch.tensor([[float(c), 0, c / 2], [0, float(c), c / 2], [0, 0, 1.0]]).expand(2, 3, 3)
        out = pr(img, k)
    got = {"pose": out.params.pose[:, :6], "cam": out.params.cam, "transl": out.transl,
           "keypoints_3d": out.keypoints_3d[:, :3]}
    for key, want in BEFORE.items():  # a tolerance for other CPUs' kernels; bit-identical on this one
        torch.testing.assert_close(got[key], torch.tensor(want), rtol=0, atol=1e-4, msg=key)


def test_average_checkpoints_is_the_weighted_mean_and_refuses_other_networks(run_a, tmp_path):
    from recovery.checkpoint import average_checkpoints, save_atomic

    a = read_checkpoint(run_a / "last.pt")
    shifted = {**a, "modules": {**a["modules"], "model": {
        k: v + 1 if v.is_floating_point() else v for k, v in a["modules"]["model"].items()}}}
    save_atomic(shifted, tmp_path / "b.pt")
    out = average_checkpoints([(run_a / "last.pt", 3.0), (tmp_path / "b.pt", 1.0)], tmp_path / "mean.pt")
    mean = read_checkpoint(out)["modules"]["model"]
    for k, v in a["modules"]["model"].items():  # (3 a + (a + 1)) / 4 = a + 1/4; counters kept
        want = v.float() + 0.25 if v.is_floating_point() else v
        torch.testing.assert_close(mean[k], want, rtol=0, atol=1e-5)
    from recovery.predictor import load_predictor

    assert load_predictor(out).config.task == "hmr_blsm"  # an inference checkpoint
    with pytest.raises(ValueError, match="another network"):  # the packaged network is another config
        average_checkpoints([(run_a / "last.pt", 1.0), ("default", 1.0)], tmp_path / "x.pt")
    with pytest.raises(ValueError, match="positive sum"):
        average_checkpoints([(run_a / "last.pt", 0.0)], tmp_path / "y.pt")
    assert not (tmp_path / "x.pt").exists() and not (tmp_path / "y.pt").exists()
