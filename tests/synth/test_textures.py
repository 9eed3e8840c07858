"""Procedural clothing textures on Anny's mesh and UV layout: determinism, coverage, garment placement."""

from __future__ import annotations

import json

import numpy as np
import pytest

from blsm import skeleton
from synth.textures import BOTTOMS, PATTERNS, SKIN_PALETTE, TOPS, Outfit, make_albedo, sample_outfit

SIZE = 256
COLOURS = {  # distinct plain colours, to tell the regions apart (linear RGB)
    "skin": (0.45, 0.3, 0.22), "top": (0.7, 0.03, 0.03), "bottoms": (0.03, 0.03, 0.7),
    "shoes": (0.03, 0.6, 0.03), "hair": (0.75, 0.7, 0.03),
}  # fmt: skip


@pytest.fixture(scope="module")
def mesh() -> dict:
    """Anny's mean body in BLSM coordinates, with its UV layout, dominant bones and joints."""
    anny = pytest.importorskip("anny")
    torch = pytest.importorskip("torch")
    from anny.skinning.skinning import apply_linear_blendshape

    from blsm.build_anny import ANNY_TO_WORLD, anny_bone_groups

    m = anny.Anny(topology="anny-noeyes-notongue")
    half = {k: torch.full((1,), 0.5, dtype=torch.float64) for k in m.phenotype_labels}
    with torch.no_grad():
        coeffs = m.get_phenotype_blendshape_coefficients(**half)
        verts = m.get_rest_vertices(coeffs)[0].numpy() @ ANNY_TO_WORLD.T
        heads = apply_linear_blendshape(m.template_bone_heads, m.bone_heads_blendshapes, coeffs)[0].numpy()
    groups = anny_bone_groups(list(m.bone_labels))
    wa = np.zeros((len(verts), len(m.bone_labels)))
    np.add.at(wa, (np.arange(len(verts))[:, None], m.vertex_bone_indices.numpy()), m.vertex_bone_weights.numpy())
    return dict(
        uv=m.texture_coordinates.numpy(), faces_uv=m.face_texture_coordinate_indices.numpy(),
        vertices=verts, faces=m.faces.numpy(),
        vertex_bones=np.stack([wa[:, g].sum(1) for g in groups], 1).argmax(1),
        bone_names=list(skeleton.BONE_NAMES), joints=(heads @ ANNY_TO_WORLD.T)[[g[0] for g in groups]],
    )  # fmt: skip


def outfit(**kw) -> Outfit:
    c = COLOURS
    colors = {"top": c["top"], "top_alt": c["top"], "bottoms": c["bottoms"], "bottoms_alt": c["bottoms"],
              "shoes": c["shoes"], "soles": c["shoes"]}  # fmt: skip
    args = dict(skin=c["skin"], top="tshirt", bottoms="trousers", shoes="shoes", colors=colors,
                patterns={"top": "plain", "bottoms": "plain", "shoes": "plain"}, hair=c["hair"])  # fmt: skip
    return Outfit(**{**args, **kw})


def albedo(mesh, o: Outfit, seed: int = 0, size: int = SIZE) -> np.ndarray:
    return make_albedo(**mesh, outfit=o, rng=np.random.default_rng(seed), size=size)


def classify(mesh, tex: np.ndarray) -> np.ndarray:
    """Region name (index into COLOURS) of the texel under every face corner: (F, 3)."""
    uv = mesh["uv"][mesh["faces_uv"]]  # (F, 3, 2)
    centroid = uv.mean(1, keepdims=True)
    uv = uv + 0.25 * (centroid - uv)  # step into the triangle, off the island border
    n = len(tex)
    rows = np.clip(((1 - uv[..., 1]) * n).astype(int), 0, n - 1)
    cols = np.clip((uv[..., 0] * n).astype(int), 0, n - 1)
    refs = np.array(list(COLOURS.values()))
    refs = np.where(refs <= 0.0031308, 12.92 * refs, 1.055 * refs ** (1 / 2.4) - 0.055) * 255
    d = np.linalg.norm(tex[rows, cols][..., None, :].astype(float) - refs, axis=-1)
    return d.argmin(-1)


def region_share(mesh, labels: np.ndarray, select: np.ndarray, region: str) -> float:
    """Fraction of the face corners at the selected vertices that show the region's colour."""
    at = select[mesh["faces"]]
    assert at.sum() > 20
    return float((labels[at] == list(COLOURS).index(region)).mean())


def bone_vertices(mesh, bone: str, lo: float = 0.0, hi: float = 1.0, child: str | None = None) -> np.ndarray:
    """Vertices of a bone whose projection onto the bone (head to the child's head) lies in [lo, hi]."""
    names = mesh["bone_names"]
    sel = mesh["vertex_bones"] == names.index(bone)
    if child is not None:
        h, t = mesh["joints"][names.index(bone)], mesh["joints"][names.index(child)]
        s = (mesh["vertices"] - h) @ (t - h) / ((t - h) @ (t - h))
        sel &= (s >= lo) & (s <= hi)
    return sel


def test_outfits_are_deterministic_json_and_cover_the_choices():
    a, b = sample_outfit(np.random.default_rng(5)), sample_outfit(np.random.default_rng(5))
    assert a == b and json.loads(json.dumps(a.to_json())) == a.to_json()
    outfits = [sample_outfit(np.random.default_rng(i)) for i in range(400)]
    assert {o.top for o in outfits} == set(TOPS) and {o.bottoms for o in outfits} == set(BOTTOMS)
    assert {o.shoes for o in outfits} == {"shoes", "barefoot"}
    assert {o.patterns["top"] for o in outfits} == set(PATTERNS)
    colours = np.array([c for o in outfits for c in o.colors.values()])
    assert colours.min() >= 0.02 and colours.max() <= 0.85
    skin = np.array([o.skin for o in outfits])
    assert skin.max() <= 0.7 and (skin[:, 0] >= skin[:, 2]).all()  # reddish, never above 0.7
    lum = skin @ [0.2126, 0.7152, 0.0722]
    palette = SKIN_PALETTE @ [0.2126, 0.7152, 0.0722]
    assert lum.max() > 0.9 * palette[0] and lum.min() < 1.3 * palette[-1]  # very light to very dark
    assert ((lum > 0.3).mean() > 0.15) and ((lum < 0.1).mean() > 0.15)


def test_outfit_rejects_unknown_garments():
    with pytest.raises(ValueError, match="top"):
        outfit(top="poncho")
    with pytest.raises(ValueError, match="patterns"):
        outfit(patterns={"top": "paisley", "bottoms": "plain", "shoes": "plain"})


def test_albedo_is_deterministic_and_filled(mesh):
    o = sample_outfit(np.random.default_rng(1))
    tex = albedo(mesh, o, seed=3)
    assert tex.shape == (SIZE, SIZE, 3) and tex.dtype == np.uint8
    assert np.array_equal(tex, albedo(mesh, o, seed=3))
    assert not np.array_equal(tex, albedo(mesh, o, seed=4))
    assert not np.array_equal(tex, albedo(mesh, sample_outfit(np.random.default_rng(2)), seed=3))
    # Covered texels and the dilated rest: nothing black (the darkest albedo is 0.01 -> sRGB ~25).
    assert tex.max(-1).min() > 15
    small = albedo(mesh, o, size=8)
    assert small.shape == (8, 8, 3) and small.max(-1).min() > 15


def test_garments_sit_on_the_right_body_parts(mesh):
    v, j, names = mesh["vertices"], mesh["joints"], mesh["bone_names"]
    jy = {n: j[names.index(n)][1] for n in names}
    chest = (v[:, 2] > 0.05) & (np.abs(v[:, 0]) < 0.08) & (v[:, 1] > jy["spine_02"]) & (v[:, 1] < jy["spine_03"])
    chest &= bone_vertices(mesh, "spine_02") | bone_vertices(mesh, "spine_03")
    sole = (bone_vertices(mesh, "ankle_l") | bone_vertices(mesh, "ankle_r")) & (v[:, 1] < v[:, 1].min() + 0.01)
    head = bone_vertices(mesh, "head")
    face = head & (v[:, 2] > j[names.index("head")][2] + 0.06) & (v[:, 1] > jy["head"]) & (v[:, 1] < jy["head"] + 0.08)
    crown = head & (v[:, 1] > v[head, 1].max() - 0.03)
    forearm = bone_vertices(mesh, "elbow_l", 0.2, 0.8, "wrist_l") | bone_vertices(mesh, "elbow_r", 0.2, 0.8, "wrist_r")
    upper = bone_vertices(mesh, "shoulder_l", 0.75, 1.0, "elbow_l") | bone_vertices(mesh, "shoulder_r", 0.75, 1.0, "elbow_r")
    shin = bone_vertices(mesh, "knee_l", 0.2, 0.8, "ankle_l") | bone_vertices(mesh, "knee_r", 0.2, 0.8, "ankle_r")
    thigh = bone_vertices(mesh, "hip_l", 0.18, 0.28, "knee_l") | bone_vertices(mesh, "hip_r", 0.18, 0.28, "knee_r")
    for seed in range(3):  # hem heights and sleeve lengths are random within their ranges
        labels = classify(mesh, albedo(mesh, outfit(), seed))
        assert region_share(mesh, labels, chest, "top") > 0.97
        assert region_share(mesh, labels, sole, "shoes") > 0.97
        assert region_share(mesh, labels, face, "skin") > 0.97
        assert region_share(mesh, labels, crown, "hair") > 0.97
        assert region_share(mesh, labels, forearm, "skin") > 0.97  # a t-shirt's sleeves are short
        assert region_share(mesh, labels, upper, "skin") > 0.9
        assert region_share(mesh, labels, shin, "bottoms") > 0.97
        labels = classify(mesh, albedo(mesh, outfit(top="longsleeve", bottoms="shorts", shoes="barefoot"), seed))
        assert region_share(mesh, labels, forearm, "top") > 0.97
        assert region_share(mesh, labels, shin, "skin") > 0.97
        assert region_share(mesh, labels, thigh, "bottoms") > 0.97
        assert region_share(mesh, labels, sole, "skin") > 0.97
        labels = classify(mesh, albedo(mesh, outfit(top="tank"), seed))
        assert region_share(mesh, labels, chest, "top") > 0.97
        assert region_share(mesh, labels, bone_vertices(mesh, "shoulder_l", 0.2, 1.0, "elbow_l"), "skin") > 0.97


def test_garment_borders_ignore_uv_seams(mesh):
    """A vertex on a UV seam has several texture coordinates: all of them show the same region."""
    vert, n = mesh["faces"].ravel(), len(mesh["vertices"])
    copies = np.bincount(np.unique(np.stack([vert, mesh["faces_uv"].ravel()], 1), axis=0)[:, 0], minlength=n)
    seam = copies > 1
    assert seam.sum() > 500
    for top, bottoms in (("tshirt", "shorts"), ("tank", "capris"), ("longsleeve", "skirt")):
        labels = classify(mesh, albedo(mesh, outfit(top=top, bottoms=bottoms), size=512)).ravel()
        lo, hi = np.full(n, 99), np.full(n, -1)
        np.minimum.at(lo, vert, labels)
        np.maximum.at(hi, vert, labels)
        mixed = lo != hi  # corners around the vertex disagree: a garment border passes through it
        print(top, bottoms, mixed[seam].mean(), mixed[~seam].mean())
        assert mixed[seam].mean() < 0.02


def test_bad_inputs_raise_naming_the_argument(mesh):
    o = outfit()
    bad = {
        "uv": mesh["uv"][:, :1], "faces_uv": mesh["faces_uv"] + len(mesh["uv"]),
        "vertices": mesh["vertices"][:, :2], "faces": mesh["faces"][:-1],
        "vertex_bones": mesh["vertex_bones"][:-1], "joints": mesh["joints"][:-1],
        "bone_names": mesh["bone_names"][:-1] + ["tail"],
    }  # fmt: skip
    for name, value in bad.items():
        with pytest.raises(ValueError, match=f"^{name}"):
            make_albedo(**{**mesh, name: value}, outfit=o, rng=np.random.default_rng(0), size=16)
    uv = mesh["uv"].copy()
    uv[0, 1] = 1.01
    with pytest.raises(ValueError, match="^uv"):
        make_albedo(**{**mesh, "uv": uv}, outfit=o, rng=np.random.default_rng(0), size=16)
    uv[0, 1] = 1.0005  # within tolerance
    make_albedo(**{**mesh, "uv": uv}, outfit=o, rng=np.random.default_rng(0), size=16)
    for size in (4, 7, 16.0):
        with pytest.raises(ValueError, match="^size"):
            make_albedo(**mesh, outfit=o, rng=np.random.default_rng(0), size=size)
