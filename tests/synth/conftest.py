from __future__ import annotations

from pathlib import Path

import pytest
from tiny_run import TINY

from synth.generate import generate


@pytest.fixture(scope="session")
def rest_body(model) -> dict:
    """The model's mean body at rest (BLSM topology): vertices, faces, skinning, joints, bone
    names and UV layout (the hair's and the garments' tests grow and dress it)."""
    import numpy as np
    import torch

    with torch.no_grad():
        out = model(pose=torch.zeros(1, 47))
    return {
        "vertices": out.template[0].numpy().astype(np.float64), "faces": model.faces.numpy(),
        "weights": model.weights.numpy(), "joints": out.rest_joints[0].numpy(), "names": list(model.bone_names),
        "uv": model.uvs.numpy(), "faces_uv": model.faces_uv.numpy(),
    }  # fmt: skip


@pytest.fixture(scope="session")
def tiny(tmp_path_factory) -> Path:
    """:data:`tiny_run.TINY` generated once for the session (tests copy it before changing it)."""
    out = tmp_path_factory.mktemp("tiny")
    generate(TINY, out, progress=False)
    return out
