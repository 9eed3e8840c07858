"""The packaged rig (``blsm build-anny --rig``): the fixed starting point the packaged model is learnt from."""

from __future__ import annotations

import numpy as np

from blsm import io
from blsm.build_anny import rig_of
from blsm.model import DEFAULT_MODEL, DEFAULT_RIG


def test_packaged_rig_has_no_blendshapes_and_the_model_topology():
    rig, model = io.read_model(DEFAULT_RIG), io.read_model(DEFAULT_MODEL)
    assert rig.meta["name"] == "blsm-rig"
    assert not rig.arrays["bone_correctives"].any() and not rig.arrays["shape_basis"].any()
    # The learnt model keeps the rig's topology, parts and keypoint definitions.
    for key in ("faces", "vertex_parts", "vertex_mirror", "keypoint_vertices", "faces_uv", "uvs"):
        np.testing.assert_array_equal(rig.arrays[key], model.arrays[key], err_msg=key)
    assert rig.dof_table_yaml == model.dof_table_yaml


def test_rig_of_strips_only_the_blendshapes(tmp_path):
    data = io.read_model(DEFAULT_MODEL)
    rig = rig_of(data)
    assert not rig.arrays["bone_correctives"].any()
    assert rig.arrays["shape_basis"].shape == (1, *data.arrays["template"].shape)
    for key in ("template", "weights", "heads", "frames", "bone_basis", "faces"):
        np.testing.assert_array_equal(rig.arrays[key], data.arrays[key], err_msg=key)
    io.save_model(rig, tmp_path / "rig.npz")  # a valid model file
    assert io.read_model(tmp_path / "rig.npz").meta["build_report"]["rig_of"].startswith(data.meta["name"])
