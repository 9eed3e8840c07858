"""Skin, face and hand detail (synth/skin_detail.py): off is today's texture, features land where the
face's keypoints are, eyeballs close the sockets only, choices by phenotype, bad input, config."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from test_textures import SIZE, mesh, outfit  # noqa: F401  (mesh: Anny's mean body, a fixture)

from blsm.color import srgb_to_linear
from synth import skin_detail as sd
from synth.raster import rasterise_uv
from synth.textures import make_albedo

LUM = np.array([0.2126, 0.7152, 0.0722])


@pytest.fixture(scope="module")
def face(mesh) -> dict:  # noqa: F811
    """The BLSM face keypoints on ``mesh``: the packaged model's keypoint vertices, embedded on Anny."""
    import blsm
    from blsm.build_anny import barycentric_interpolate
    from synth.subjects import _anny_embedding

    model = blsm.load()
    tri, bary = _anny_embedding(model)
    target = barycentric_interpolate(mesh["vertices"], mesh["faces"], tri, bary)
    kv, kw = model.keypoint_vertices.numpy(), model.keypoint_weights.numpy()
    names = list(model.keypoint_names)
    return {k: (target[kv[names.index(k)]] * kw[names.index(k)][:, None]).sum(0) for k in sd.FACE_POINTS}


@pytest.fixture(scope="module")
def fitted(mesh, face) -> tuple[dict, sd.SkinDetail]:  # noqa: F811
    """``mesh`` with eyeballs and a plain detail (no beard, freckles, moles or flush) to paint on it."""
    verts, detail = sd.subject_detail(0, "s", mesh["vertices"], mesh["faces"], mesh["vertex_bones"],
                                      mesh["bone_names"], face, outfit().skin, (0.02, 0.02, 0.02),
                                      {"gender": 1.0, "age_years": 30.0})  # fmt: skip
    plain = dataclasses.replace(detail, beard="none", beard_density=0.0, freckles=0.0, moles=0, flush=0.0)
    return {**mesh, "vertices": verts}, plain


def texel_positions(m: dict, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(N,) flat texel indices and (N, 3) rest positions of the covered texels."""
    texels, f, bary = rasterise_uv(np.clip(m["uv"], 0, 1), m["faces_uv"], size)
    corners = m["faces"][f]
    return texels, sum(bary[:, k, None] * m["vertices"][corners[:, k]] for k in range(3))


def test_off_is_todays_texture_and_on_paints_only_skin(mesh, face):  # noqa: F811
    o = outfit()
    today = make_albedo(**mesh, outfit=o, rng=np.random.default_rng(3), size=64)
    off = make_albedo(**mesh, outfit=o, rng=np.random.default_rng(3), size=64, detail=None)
    assert today.tobytes() == off.tobytes()
    # On: the outfit's generator is left exactly where off leaves it (the detail draws from its own),
    # and only skin texels change.
    d = sd.sample_detail(sd.detail_rng(0, "s"), face, o.skin, o.hair, {"gender": 0.0, "age_years": 40})
    r_off, r_on = np.random.default_rng(3), np.random.default_rng(3)
    off = make_albedo(**mesh, outfit=o, rng=r_off, size=SIZE)
    on = make_albedo(**mesh, outfit=o, rng=r_on, size=SIZE, detail=d)
    assert r_off.bit_generator.state == r_on.bit_generator.state
    changed = (off != on).any(-1)
    assert changed.mean() > 0.05
    skin_srgb = np.round(255 * np.where(np.asarray(o.skin) <= 0.0031308, 12.92 * np.asarray(o.skin),
                                        1.055 * np.asarray(o.skin) ** (1 / 2.4) - 0.055))  # fmt: skip
    assert np.abs(off[changed].astype(float) - skin_srgb).max() < 12  # every changed texel was skin


def test_features_land_at_the_keypoints(fitted, face):
    m, d = fitted
    o = outfit(hair=(0.03, 0.02, 0.015))
    texels, p = texel_positions(m, 512)
    tex = [make_albedo(**m, outfit=o, rng=np.random.default_rng(0), size=512, detail=x) for x in (None, d)]
    a, b = (srgb_to_linear(t / 255).reshape(-1, 3)[texels] for t in tex)
    ratio = (b @ LUM) / np.maximum(a @ LUM, 1e-6)
    redder = (b[:, 0] / np.maximum(b[:, 1], 1e-6)) / (a[:, 0] / np.maximum(a[:, 1], 1e-6))
    e = np.linalg.norm(face["left_eye"] - face["right_eye"]) / 2
    for name in ("left_eye", "right_eye"):
        k = face[name]
        near = np.linalg.norm(p - k, axis=1) < 0.7 * e
        assert (near & (b @ LUM < 0.03)).sum() >= 5, name  # pupil, iris and lash line
        assert (near & (b @ LUM > 0.4)).sum() >= 5, name  # the white of the eye
        # The eyebrow: the darkest row of a band above the eye, 0.3-1 e (9-30 mm) above it.
        above = (p[:, 1] - k[1]) / e
        column = np.abs(p[:, 0] - k[0]) < 0.4 * e
        column &= (p[:, 2] > k[2] - 0.5 * e) & (0.2 < above) & (above < 2.5)
        rows = np.round(above[column] / 0.1).astype(int)
        dark = np.bincount(rows, ratio[column] < 0.6) / np.maximum(np.bincount(rows), 1)
        assert dark.max() > 0.4 and 0.3 <= dark.argmax() * 0.1 <= 1.0, (name, dark.round(2))
        assert dark[15:].max() < 0.05, name  # no dark paint on the forehead
    # The lips: the redder texels lie centred below the nose keypoint.
    nose = face["nose"]
    lips = (redder > 1.15) & (np.abs(p[:, 0]) < 1.5 * e) & (p[:, 2] > nose[2] - 2 * e) & (p[:, 1] < nose[1])
    assert lips.sum() > 30
    centre = p[lips].mean(0)
    assert abs(centre[0] - nose[0]) < 0.15 * e and 0.8 * e < nose[1] - centre[1] < 2.5 * e


def test_beard_darkens_the_chin_only(fitted, face):
    m, detail = fitted
    o = outfit(hair=(0.02, 0.02, 0.02))
    size = 256
    texels, p = texel_positions(m, size)
    lum = {}
    for beard in ("none", "beard"):
        d = dataclasses.replace(detail, beard=beard, beard_density=1.0 if beard != "none" else 0.0)
        tex = make_albedo(**m, outfit=o, rng=np.random.default_rng(0), size=size, detail=d)
        lum[beard] = srgb_to_linear(tex / 255).reshape(-1, 3)[texels] @ LUM
    nose, e = face["nose"], np.linalg.norm(face["left_eye"] - face["right_eye"]) / 2
    chin = (np.abs(p[:, 0] - nose[0]) < 0.3 * e) & (np.abs(nose[1] - p[:, 1] - 2.6 * e) < 0.2 * e)
    chin &= p[:, 2] > nose[2] - 1.5 * e
    brow = (np.abs(p[:, 0] - nose[0]) < 0.3 * e) & (np.abs(p[:, 1] - face["left_eye"][1] - 1.5 * e) < 0.3 * e)
    brow &= p[:, 2] > nose[2] - 2 * e
    assert chin.sum() > 5 and brow.sum() > 5
    assert np.median(lum["beard"][chin] / lum["none"][chin]) < 0.5
    assert np.allclose(lum["beard"][brow], lum["none"][brow])


def test_fit_eyeballs_moves_the_sockets_forward_only(mesh, face, fitted):  # noqa: F811
    m, detail = fitted
    moved = np.linalg.norm(m["vertices"] - mesh["vertices"], axis=1) > 1e-9
    e = np.linalg.norm(face["left_eye"] - face["right_eye"]) / 2
    assert moved.sum() > 20
    near_eye = np.min([np.linalg.norm(mesh["vertices"] - face[k], axis=1) for k in sd.FACE_POINTS[1:3]], 0)
    assert near_eye[moved].max() < 1.5 * e
    assert (m["vertices"][moved, 2] > mesh["vertices"][moved, 2]).all()  # forward (+Z), never back
    assert set(detail.eyes) == {"left_eye", "right_eye"}
    for k, (x, y, _, r) in detail.eyes.items():
        assert np.hypot(x - face[k][0], y - face[k][1]) < 0.3 * e and 0.3 * e < r < 0.5 * e
    # A mesh with eyeballs has no socket left: fitting again changes nothing.
    head = np.isin(m["vertex_bones"], [m["bone_names"].index(b) for b in ("head", "neck")])
    again, eyes = sd.fit_eyeballs(m["vertices"], m["faces"], head, face)
    assert eyes == {} and np.array_equal(again, m["vertices"])


def test_sample_detail_follows_the_phenotype():
    face = {k: np.zeros(3) for k in sd.FACE_POINTS}
    light, darkest = (0.6, 0.44, 0.35), (0.09, 0.05, 0.035)
    d1 = sd.sample_detail(sd.detail_rng(5, "anny_0001"), face, light, (0.1, 0.05, 0.02), {"gender": 0.1})
    d2 = sd.sample_detail(sd.detail_rng(5, "anny_0001"), face, light, (0.1, 0.05, 0.02), {"gender": 0.1})
    assert d1 == d2 and d1 != sd.sample_detail(sd.detail_rng(5, "anny_0002"), face, light, (0.1,) * 3, {})
    json.dumps(d1.to_json())
    rng = np.random.default_rng(0)

    def draw(n: int, skin=light, **phenotype) -> list[sd.SkinDetail]:
        return [sd.sample_detail(rng, face, skin, (0.02,) * 3, phenotype) for _ in range(n)]

    women, boys = draw(100, gender=0.9, age_years=40), draw(100, gender=0.0, age_years=12)
    men = draw(200, gender=0.0)
    assert {d.beard for d in women + boys} == {"none"}
    assert {d.beard for d in men} == set(sd.BEARDS)
    dark = draw(100, darkest, age_years=40)
    assert all(d.freckles == 0 for d in dark) and any(d.freckles > 0 for d in women)
    blue = sd._hex(sd._IRIS_HEX)[5]
    assert not any(np.allclose(np.asarray(d.iris) / blue, np.asarray(d.iris)[0] / blue[0]) for d in dark)


def test_bad_detail_is_a_value_error(mesh, face, fitted):  # noqa: F811
    _, d = fitted
    with pytest.raises(ValueError, match="detail face must have the keypoints"):
        dataclasses.replace(d, face={k: v for k, v in d.face.items() if k != "nose"})
    with pytest.raises(ValueError, match="detail beard must be one of"):
        dataclasses.replace(d, beard="moustache")
    with pytest.raises(ValueError, match="detail brow must lie in"):
        dataclasses.replace(d, brow=1.5)
    with pytest.raises(ValueError, match=r"detail face\['nose'\] must be 3 finite numbers"):
        dataclasses.replace(d, face={**d.face, "nose": (0.0, np.nan, 0.0)})
    swapped = {**d.face, "left_eye": d.face["right_eye"], "right_eye": d.face["left_eye"]}
    with pytest.raises(ValueError, match="the nose must lie in front of the eyes"):
        make_albedo(**mesh, outfit=outfit(), rng=np.random.default_rng(0), size=32,
                    detail=dataclasses.replace(d, face=swapped))  # fmt: skip


def test_config_detail_key(tmp_path):
    from synth.config import GeneratorConfig, SubjectsConfig, load_config

    assert SubjectsConfig().detail is False
    with pytest.raises(ValueError, match="subjects.detail must be true or false"):
        SubjectsConfig(detail=1)
    with pytest.raises(ValueError, match="subjects.detail applies to source: anny only"):
        SubjectsConfig(source="folder", folder="x", detail=True)
    p = tmp_path / "c.yaml"
    p.write_text("subjects: {detail: 3}\n")
    with pytest.raises(ValueError, match="subjects.detail"):
        load_config(p)
    base, detail = (load_config(f"configs/synth/transfer/{n}.yaml") for n in ("base", "detail"))
    assert detail.subjects.detail and detail == dataclasses.replace(
        base, subjects=dataclasses.replace(base.subjects, detail=True)
    )
    assert GeneratorConfig().subjects.detail is False


def test_subjects_folder_is_stamped_with_detail(tmp_path):
    """A folder made without detail is reused with it off (the stamp unchanged) and refused with it on."""
    import blsm
    from synth.config import GeneratorConfig, SubjectsConfig
    from synth.generate import prepare_subjects
    from synth.subjects import Subject, model_fingerprint, save_subject

    model = blsm.load()
    cfg = GeneratorConfig(seed=4, subjects=SubjectsConfig(count=1, texture_size=16))
    stamp = {"model": model_fingerprint(model), "seed": 4, "texture_size": 16,
             "population": json.loads(json.dumps(dataclasses.asdict(cfg.subjects.population())))}  # fmt: skip
    v = np.eye(3, dtype=np.float32)
    s = Subject("anny_0000", v, np.array([[0, 1, 2]]), v[:, :2], np.array([[0, 1, 2]]),
                np.zeros((16, 16, 3), np.uint8), np.ones((3, 1), np.float32), v,
                {k: np.zeros(1, np.float32) for k in ("bone", "shape", "angles", "global_orient", "transl",
                                                       "displacement")}, {"made_with": stamp})  # fmt: skip
    save_subject(s, (tmp_path / "subjects").mkdir() or tmp_path / "subjects" / "anny_0000.npz")
    assert [p.name for p in prepare_subjects(cfg, tmp_path, model)] == ["anny_0000.npz"]
    on = dataclasses.replace(cfg, subjects=dataclasses.replace(cfg.subjects, detail=True))
    with pytest.raises(ValueError, match=r"subject made with other settings \(detail differs\)"):
        prepare_subjects(on, tmp_path, model)
