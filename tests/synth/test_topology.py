"""``labels.topology``: the people's vertices in a second topology (synth.topology, blsm reparam)."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
from tiny_run import TINY
from tiny_run import copy_subjects as _copy_subjects

from synth.config import GeneratorConfig, LabelsConfig
from synth.dataset import format as fmt
from synth.dataset.shards import read_shard, write_shard
from synth.generate import generate
from synth.validate import validate


@pytest.fixture(scope="module")
def permuted(tmp_path_factory):
    """The packaged model reparameterised to its own template with the vertices shuffled: W' is a
    permutation, so the second topology's vertices are the original body's, reordered."""
    from blsm import io
    from blsm.learn.reparam.model import reparameterise
    from blsm.model import DEFAULT_MODEL

    data = io.read_model(DEFAULT_MODEL)
    v, f = data.arrays["template"], data.arrays["faces"]
    perm = np.random.default_rng(0).permutation(len(v))  # new vertex i is old vertex perm[i]
    inv = np.argsort(perm)
    new, _ = reparameterise(data, v[perm], inv[f])
    path = tmp_path_factory.mktemp("topology") / "perm.npz"
    io.save_model(new, path)
    return path, perm


def test_off_by_default_no_member_no_manifest_key(tiny):
    assert "labels" not in json.loads((tiny / "manifest.json").read_text())["config"]
    assert not any(k.startswith("vertices_") for k in read_shard(tiny / "shard-000000.tar")["000000000"])


def test_topology_member_is_the_registered_body_and_validates(tiny, tmp_path, permuted, model):
    from synth.subjects import load_subject, registration_output

    path, perm = permuted
    out = tmp_path / "topo"
    out.mkdir()
    _copy_subjects(tiny, out)
    cfg = dataclasses.replace(TINY, num=2, labels=LabelsConfig(topology=str(path), topology_name="perm"))
    generate(cfg, out, progress=False)
    rep = validate(out)
    assert rep.samples == 2 and rep.failures == []
    sample = fmt.decode_sample(read_shard(out / "shard-000000.tar")["000000000"])
    doc, verts = sample["json"], sample["vertices_perm"]
    assert verts.shape == (len(doc["people"]), 7002, 3) and verts.dtype == np.float32
    for i, p in enumerate(doc["people"]):
        s = load_subject(out / "subjects" / f"{p['subject']}.npz")
        b = {k: np.asarray(p["blsm"][k], np.float32) for k in ("pose", "global_orient", "transl")}
        body = registration_output(model, s.registration, b["pose"], global_orient=b["global_orient"], transl=b["transl"])[0]
        assert np.abs(verts[i] - body.numpy()[perm]).max() < 1e-4

    # a moved vertex is found
    bad = tmp_path / "bad"
    shutil.copytree(out, bad)
    shard = bad / "shard-000000.tar"
    samples = read_shard(shard)
    v = fmt.decode_npy_gz(samples["000000000"]["vertices_perm.npy.gz"]).copy()
    v[0, 100, 1] += 0.001
    samples["000000000"]["vertices_perm.npy.gz"] = fmt.encode_npy_gz(v)
    digest = write_shard(shard, [(int(k), x) for k, x in sorted(samples.items())])
    man = json.loads((bad / "manifest.json").read_text())
    man["shards"]["shard-000000.tar"]["sha256"] = digest
    (bad / "manifest.json").write_text(json.dumps(man))
    failures = validate(bad).failures
    assert len(failures) == 1 and "vertices_perm differs from the rebuilt body by 1.000 mm" in failures[0]


def test_config_errors():
    with pytest.raises(ValueError, match="topology_name"):
        LabelsConfig(topology="x.npz", topology_name="Bad-Name")
    with pytest.raises(ValueError, match="posable pipeline"):
        GeneratorConfig(pipeline="raw", labels=LabelsConfig(topology="x.npz"))
