"""synth.garments: cloth over the painted garments, sunk elsewhere; skirts around the legs; posed
with the body; labels stay the body's and ``synth validate`` rebuilds the clothes."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
import torch
from tiny_run import TINY

from synth.config import GarmentsConfig
from synth.garments import (
    INSET,
    RINGS,
    SEGMENTS,
    GarmentSpec,
    build_garments,
    pose_garments,
    sample_garments,
    skirt_faces,
)
from synth.textures import Outfit, draw_cuts, make_albedo, sample_outfit, vertex_labels


@pytest.fixture(scope="module")
def body(rest_body):
    """The model's mean body at rest, its skinning and UV layout (``conftest.rest_body``)."""
    return rest_body


def _outfit(top: str, bottoms: str, seed: int = 0) -> Outfit:
    o = sample_outfit(np.random.default_rng(seed))
    return dataclasses.replace(o, top=top, bottoms=bottoms, shoes="shoes")


def _labels(body, outfit: Outfit, seed: int = 1) -> np.ndarray:
    cuts = draw_cuts(outfit, np.random.default_rng(seed))
    return vertex_labels(body["vertices"], body["weights"].argmax(1), body["names"], body["joints"], outfit, cuts)


def _spec(outfit: Outfit, fit: str = "loose", **kw) -> GarmentSpec:
    spec = sample_garments(np.random.default_rng(5), outfit, {fit: 1.0}, jacket=0.0, dress=0.0)
    return dataclasses.replace(spec, **kw)


def _signed_distance(body, points: np.ndarray) -> np.ndarray:
    """trimesh's signed distance to the body (positive inside)."""
    import trimesh

    mesh = trimesh.Trimesh(body["vertices"], body["faces"], process=False)
    return trimesh.proximity.signed_distance(mesh, points)


def test_painting_reports_its_borders_and_is_unchanged_by_asking(body):
    outfit = _outfit("tshirt", "shorts")
    args = (body["uv"], body["faces_uv"], body["vertices"], body["faces"], body["weights"].argmax(1), body["names"],
            body["joints"], outfit)  # fmt: skip
    plain = make_albedo(*args, np.random.default_rng(3), 32)
    cuts: dict[str, float] = {}
    asked = make_albedo(*args, np.random.default_rng(3), 32, cuts_out=cuts)
    assert np.array_equal(plain, asked)
    assert cuts == draw_cuts(outfit, np.random.default_rng(3))
    assert {"waist", "leg_hem", "sleeve", "shoe_line"} <= set(cuts)


def test_vertex_labels_follow_the_garment_types(body):
    names, vb = body["names"], body["weights"].argmax(1)
    forearm = np.isin(vb, [names.index("elbow_l"), names.index("elbow_r")])
    shin = np.isin(vb, [names.index("knee_l"), names.index("knee_r")])
    long_trousers = _labels(body, _outfit("longsleeve", "trousers"))
    short_shorts = _labels(body, _outfit("tank", "shorts"))
    assert (long_trousers[forearm] == 1).mean() > 0.8 and (long_trousers[shin] == 2).mean() > 0.8
    assert (short_shorts[forearm] == 0).mean() > 0.9 and (short_shorts[shin] == 2).mean() < 0.05


@pytest.mark.parametrize("fit", ["fitted", "loose"])
def test_cloth_stands_off_where_painted_and_sinks_under_the_skin_elsewhere(body, fit):
    outfit = _outfit("tshirt", "trousers")
    label = _labels(body, outfit)
    spec = _spec(outfit, fit)
    g = build_garments(body["vertices"], body["faces"], body["weights"], label, body["names"], body["joints"],
                       outfit.colors, spec)  # fmt: skip
    assert g.layer.shape == body["vertices"].shape and g.skirt is None
    off = ((g.layer - body["vertices"]) * _normals(body)).sum(1)
    skin = label == 0
    assert np.allclose(off[skin], -INSET, atol=1e-6)
    cloth = np.isin(label, (1, 2)) & (off > 0)
    assert cloth.sum() > 0.8 * np.isin(label, (1, 2)).sum()  # all but the hems' vertices (on the skin)
    sd = _signed_distance(body, g.layer[cloth].astype(np.float64))
    assert (sd < 0).mean() > 0.97  # outside the body
    # A loose top hangs off its hem more than off the chest.
    names, vb = body["names"], body["weights"].argmax(1)
    trunk = (label == 1) & np.isin(vb, [names.index(b) for b in ("pelvis", "spine_01", "spine_02", "spine_03")])
    y = body["vertices"][:, 1]
    lo, hi = y[trunk].min(), y[trunk].max()
    low, chest = trunk & (y < lo + 0.15 * (hi - lo)), trunk & (y > lo + 0.7 * (hi - lo))
    assert low.sum() > 20 and chest.sum() > 20
    if fit == "loose":
        assert np.median(off[low]) > np.median(off[chest]) + 0.01


def test_skirt_hangs_around_the_legs_from_the_waist(body):
    outfit = _outfit("tshirt", "skirt")
    label = _labels(body, outfit)
    spec = _spec(outfit, "regular", skirt="dress", length=1.3)
    g = build_garments(body["vertices"], body["faces"], body["weights"], label, body["names"], body["joints"],
                       outfit.colors, spec)  # fmt: skip
    assert g.skirt.shape == (RINGS * SEGMENTS, 3) and skirt_faces().max() == RINGS * SEGMENTS - 1
    assert np.allclose(g.skirt_weights.sum(1), 1.0, atol=1e-5)
    assert (_signed_distance(body, g.skirt.astype(np.float64)) < 0).all()  # no skirt vertex inside the body
    rings = g.skirt.reshape(RINGS, SEGMENTS, 3)
    radius = np.linalg.norm(rings[..., [0, 2]] - rings[..., [0, 2]].mean(1, keepdims=True), axis=-1).mean(1)
    assert (np.diff(radius) > -1e-6).all()  # A-line: never narrower lower down
    assert np.allclose(g.skirt_colours, np.asarray(outfit.colors["top"]), atol=0.1)  # a dress: the top's colour
    # The layer has no cloth on the legs under the skirt.
    legs = np.isin(body["weights"].argmax(1), [body["names"].index(b) for b in ("knee_l", "knee_r")])
    assert (((g.layer - body["vertices"]) * _normals(body)).sum(1)[legs & (label == 2)] < 0).all()


def test_clothes_pose_with_the_body(body, model):
    outfit = _outfit("longsleeve", "skirt")
    spec = _spec(outfit, "regular", skirt="skirt", jacket=0.02)
    label = _labels(body, outfit)
    g = build_garments(body["vertices"], body["faces"], body["weights"], label, body["names"], body["joints"],
                       outfit.colors, spec)  # fmt: skip
    torch.manual_seed(0)
    with torch.no_grad():
        out = model(pose=0.5 * torch.randn(1, 47))
    tr = out.skinning_transforms[0].numpy()
    layer, skirt = pose_garments(g, body["weights"], tr)
    from blsm.lbs import linear_blend_skinning

    t = torch.as_tensor(tr)[None]
    posed_body = linear_blend_skinning(torch.as_tensor(body["vertices"], dtype=torch.float32)[None],
                                       torch.as_tensor(body["weights"]), t[..., :3], t[..., 3])[0].numpy()  # fmt: skip
    # The layer is the body plus its blended offset: as far from the posed body as at rest (rigid parts).
    rest_gap = np.linalg.norm(g.layer - body["vertices"], axis=1)
    posed_gap = np.linalg.norm(layer - posed_body, axis=1)
    rigid = body["weights"].max(1) > 0.999
    assert np.allclose(rest_gap[rigid], posed_gap[rigid], atol=1e-4)
    assert skirt.shape == g.skirt.shape and np.isfinite(skirt).all()


def test_spec_round_trips_and_bad_specs_are_refused():
    spec = sample_garments(np.random.default_rng(1), _outfit("longsleeve", "skirt"), {"regular": 1}, 1.0, 1.0)
    assert spec.jacket > 0 and spec.skirt == "dress"
    assert GarmentSpec.from_json(json.loads(json.dumps(spec.to_json()))) == spec
    with pytest.raises(ValueError, match="fit"):
        dataclasses.replace(spec, fit="baggy")
    with pytest.raises(ValueError, match="lacks"):
        GarmentSpec.from_json({"fit": "loose"})
    with pytest.raises(ValueError, match="fits"):
        sample_garments(np.random.default_rng(1), _outfit("tank", "shorts"), {"baggy": 1.0}, 0.0, 0.0)
    with pytest.raises(ValueError, match="garments.jacket"):
        GarmentsConfig(jacket=1.5)


def _normals(body) -> np.ndarray:
    from blsm.mesh import vertex_normals

    return vertex_normals(body["vertices"], body["faces"].astype(np.int64))


def test_generate_with_clothes_validates_and_keeps_the_bodys_labels(tiny, tmp_path):
    """The tiny run again with garments (its subjects reused): 0 validation failures, each
    person's subject and BLSM pose the same as without clothes, more mask pixels."""
    from synth.dataset.format import decode_sample
    from synth.dataset.shards import read_shard
    from synth.generate import generate
    from synth.validate import validate

    out = tmp_path / "clothed"
    out.mkdir()
    shutil.copytree(tiny / "subjects", out / "subjects")
    cfg = dataclasses.replace(TINY, garments=GarmentsConfig(enabled=True, jacket=0.5, dress=0.5))
    generate(cfg, out, progress=False, resume=True)
    rep = validate(out)
    assert rep.samples == TINY.num and rep.failures == []

    def samples(d):
        out = {}
        for shard in sorted(d.glob("shard-*.tar")):
            for key, fields in read_shard(shard).items():
                out[key] = decode_sample(fields)
        return out

    plain, clothed = samples(tiny), samples(out)
    assert plain.keys() == clothed.keys()
    more = 0
    for k in plain:
        a, b = plain[k]["json"]["people"], clothed[k]["json"]["people"]
        assert [p["subject"] for p in a] == [p["subject"] for p in b]
        for p, q in zip(a, b):
            assert p["blsm"]["pose"] == q["blsm"]["pose"] and p["blsm"]["bone"] == q["blsm"]["bone"]
            # Leaf bones' lengths come from posed keypoints placed elsewhere: float32 round-off.
            assert np.allclose(p["bone_lengths"], q["bone_lengths"], atol=1e-5)
            assert "garments" in q and "garments" not in p
        more += int((clothed[k]["mask"] > 0).sum() > (plain[k]["mask"] > 0).sum())
    assert more >= TINY.num // 2
