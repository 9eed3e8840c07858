"""recovery.checkpoint: checkpoints hold no module path, so one written before issue 33 moved the
modules (the packaged ``default``) loads and predicts the numbers it predicted then."""

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


# The packaged network's prediction for two fixed random crops, computed with the layout before
# issue 33 (recovery.predictor.load_predictor("default") at commit 3f1a343, one CPU thread).
BEFORE = {
    "pose": [[-0.47306936979293823, -0.03259843960404396, 0.000547290313988924, -0.15620605647563934,
              -0.03307543694972992, -0.0014586972538381815],
             [-0.5098181962966919, 0.01459423452615738, -0.029470067471265793, -0.13548538088798523,
              -0.008026475086808205, -0.018094755709171295]],
    "cam": [[0.9630827903747559, -0.07428421080112457, -0.04226470738649368],
            [0.9883627891540527, -0.07091651111841202, -0.040121059864759445]],
    "transl": [[-0.07713168114423752, -0.04388480633497238, 2.076664686203003],
               [-0.07175152003765106, -0.040593471378088, 2.0235483646392822]],
    "keypoints_3d": [[[0.0, 0.0, 0.0], [-0.014456664212048054, -0.06539347767829895, -0.016086800023913383],
                      [-0.03296429663896561, -0.16605056822299957, -0.10239731520414352]],
                     [[0.0, 0.0, 0.0], [-0.0049962494522333145, -0.0660516619682312, -0.002491082064807415],
                      [-0.019349077716469765, -0.17889027297496796, -0.06213003024458885]]],
}


def test_checkpoint_written_before_the_move_predicts_the_same_numbers():
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
