"""synth.hair: strands on the scalp, off the skin, posed with the head; specs round-trip."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from synth.hair import (
    NUM_STRANDS,
    POINTS,
    STYLES,
    HairSpec,
    build_hair,
    hair_faces,
    num_vertices,
    pose_hair,
    sample_hair,
)


@pytest.fixture(scope="module")
def body(rest_body):
    """The model's mean body at rest (BLSM topology) and its skinning (``conftest.rest_body``)."""
    return rest_body


def _spec(style: str, seed: int = 3) -> HairSpec:
    return sample_hair(np.random.default_rng(seed), {style: 1.0}, (0.2, 0.12, 0.05))


@pytest.fixture(scope="module")
def hairs(body):
    return {s: build_hair(body["vertices"], body["faces"], body["weights"], body["names"], body["joints"], _spec(s))
            for s in STYLES}  # fmt: skip


def _signed_distance(body, points: np.ndarray) -> np.ndarray:
    """trimesh's signed distance to the body (positive inside)."""
    import trimesh

    mesh = trimesh.Trimesh(body["vertices"], body["faces"], process=False)
    return trimesh.proximity.signed_distance(mesh, points)


@pytest.mark.parametrize("style", STYLES)
def test_strands_root_on_the_scalp_and_stay_out_of_the_body(body, hairs, style):
    h = hairs[style]
    assert h.faces is hair_faces() and h.vertices.shape == (num_vertices(), 3)
    assert np.isfinite(h.vertices).all() and np.allclose(h.weights.sum(1), 1.0, atol=1e-5)
    centre = h.vertices.reshape(NUM_STRANDS, POINTS, 2, 3).mean(2)
    rng = np.random.default_rng(0)
    pick = rng.choice(NUM_STRANDS, 150, replace=False)
    roots = centre[pick, 0]
    d_root = _signed_distance(body, roots)
    assert (d_root < 0).all() and (d_root > -0.008).all()  # on the scalp, outside by millimetres
    head = body["joints"][body["names"].index("head")]
    assert (roots[:, 1] > head[1] - 0.08).all()  # the scalp, not the face or the body
    d_all = _signed_distance(body, centre[pick].reshape(-1, 3))
    assert d_all.max() < 0.002, f"{(d_all > 0.002).sum()} strand points inside the body"


def test_styles_differ_as_described(hairs, body):
    strands = {s: hairs[s].vertices.reshape(NUM_STRANDS, POINTS, 2, 3).mean(2) for s in STYLES}
    length = {s: np.linalg.norm(np.diff(v, axis=1), axis=2).sum(1) for s, v in strands.items()}
    assert np.median(length["long"]) > 2.5 * np.median(length["short"])
    low = {s: np.percentile(v[:, -1, 1], 10) for s, v in strands.items()}
    neck = body["joints"][body["names"].index("neck")][1]
    assert low["long"] < neck < low["short"]  # long hair hangs below the neck, short hair does not
    tips = strands["tied"][:, -1]
    gathered = np.linalg.norm(tips - np.median(tips, 0), axis=1) < 0.08  # into one ponytail
    assert gathered.mean() > 0.99
    assert (tips[gathered, 2] < body["joints"][body["names"].index("head")][2]).all()  # behind the head
    bend = {s: np.linalg.norm(np.diff(v, 2, axis=1), axis=2).mean() for s, v in strands.items()}
    assert bend["curly"] > 2 * bend["short"]


def test_the_same_spec_grows_the_same_hair_and_survives_json(body):
    spec = _spec("long", seed=11)
    assert HairSpec.from_json(spec.to_json()) == spec
    a = build_hair(body["vertices"], body["faces"], body["weights"], body["names"], body["joints"], spec)
    b = build_hair(body["vertices"], body["faces"], body["weights"], body["names"], body["joints"], HairSpec.from_json(spec.to_json()))
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.weights, b.weights)
    c = build_hair(body["vertices"], body["faces"], body["weights"], body["names"], body["joints"], _spec("long", seed=12))
    assert not np.array_equal(a.vertices, c.vertices)


def test_posed_hair_roots_follow_the_scalp(model, body, hairs):
    names = body["names"]
    x = torch.zeros(1, 47)
    with torch.no_grad():
        rest = model(pose=x)
        x[0] = torch.linspace(-1.5, 1.5, 47)  # every atom moved, the neck and head included
        out = model(pose=x)
    tr = out.skinning_transforms[0]
    from blsm.lbs import linear_blend_skinning

    posed_body = linear_blend_skinning(rest.template, model.weights, tr[None, :, :, :3], tr[None, :, :, 3])[0].numpy()
    h = hairs["short"]
    posed = pose_hair(h, tr.numpy())
    roots = posed.reshape(NUM_STRANDS, POINTS, 2, 3).mean(2)[:, 0]
    rest_roots = h.vertices.reshape(NUM_STRANDS, POINTS, 2, 3).mean(2)[:, 0]
    head = names.index("head")
    moved = np.linalg.norm(roots - rest_roots, axis=1).min()
    assert moved > 0.01  # the head moved, and the hair with it
    from scipy.spatial import cKDTree

    d_rest = cKDTree(body["vertices"]).query(rest_roots)[0]
    d_posed = cKDTree(posed_body).query(roots)[0]
    assert np.abs(d_posed - d_rest).max() < 0.003  # still on the scalp
    assert model.weights.numpy()[:, head].max() == 1.0


def test_sample_hair_follows_the_weights_and_refuses_none():
    rng = np.random.default_rng(0)
    styles = [sample_hair(rng, {"short": 1.0, "curly": 3.0}, (0.1, 0.1, 0.1)).style for _ in range(400)]
    assert set(styles) == {"short", "curly"} and 0.65 < styles.count("curly") / 400 < 0.85
    with pytest.raises(ValueError, match="at least one style"):
        sample_hair(rng, {"short": 0.0}, (0.1, 0.1, 0.1))
    with pytest.raises(ValueError, match="hair style must be one of"):
        HairSpec("mohawk", 0.1, 0.01, 0.01, 0.0, (0.1, 0.1, 0.1), 0)


def _frame_on(tri: np.ndarray, size: int = 4):
    """A label pass whose every pixel centre hits face 0 of triangle ``tri`` (camera at the origin
    looking down +z, focal 4 px): positions on the triangle's plane z = tri[0, 2]."""
    from blsm.camera import Camera
    from synth.render import Frame

    K = np.array([[4.0, 0, size / 2], [0, 4.0, size / 2], [0, 0, 1]])
    cam = Camera(K=K, R=np.eye(3), t=np.zeros(3), width=size, height=size)
    v, u = np.mgrid[0:size, 0:size] + 0.5
    z = tri[0, 2]
    pos = np.stack([(u - size / 2) / 4.0 * z, (v - size / 2) / 4.0 * z, np.full(u.shape, z)], -1)
    hit = np.ones((size, size), bool)
    return cam, Frame(rgb=np.zeros((size, size, 3), np.float32), alpha=np.ones((size, size), np.float32), hit=hit,
                      position=pos.astype(np.float32), face=np.zeros((size, size), np.int64))


def test_hair_pixels_are_the_head_hide_surface_keypoints_not_joints():
    from synth.labels import person_labels

    big = np.array([[-5.0, -5.0, 0.0], [5.0, -5.0, 0.0], [0.0, 5.0, 0.0]])
    body, hair = big + [0, 0, 1.02], big + [0, 0, 1.0]  # the hair 2 cm in front of the skin
    cam, frame = _frame_on(hair)
    person = {
        "vertices": body, "faces": np.array([[0, 1, 2]]), "face_bones": np.array([5]),
        "keypoints": np.array([[0.01, 0.01, 1.02], [0.01, 0.01, 1.1]]),  # an ear on the skin, a joint inside
        "hair_vertices": hair, "hair_faces": np.array([[0, 1, 2]]), "hair_bone": 5,
    }  # fmt: skip
    bone_to_part = np.zeros(20, np.int64)
    out = person_labels(frame, cam, [person], bone_to_part, [{5}, {5}], np.array([False, True]))
    assert out["unassigned"] == 0 and (out["mask"] == 1).all() and (out["bones"] == 6).all()
    assert (out["corr"][..., 0] == 1).all()  # the hair's face 0 follows the body's one face
    np.testing.assert_allclose(out["depth"], 1.0, atol=1e-6)
    assert out["people"][0]["visible"].tolist() == [False, True]
    # Without hair the same ray hits the skin and the ear is visible.
    cam, frame = _frame_on(body)
    bald = {k: v for k, v in person.items() if not k.startswith("hair")}
    out = person_labels(frame, cam, [bald], bone_to_part, [{5}, {5}], np.array([False, True]))
    assert (out["corr"][..., 0] == 0).all() and out["people"][0]["visible"].tolist() == [True, True]
