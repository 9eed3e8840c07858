"""Scan import: folders of textured / vertex-coloured scans with a registration become rigged subjects.

The scans are BLSM meshes themselves, so the registration and the rig must reproduce them exactly.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from PIL import Image

from blsm import io as blsm_io
from blsm.joint_limits import unconstrained_from_angles
from synth.scans import import_scan, import_scans, load_scan
from synth.subjects import load_subject, pose_subject, registration_output, save_subject

torch.set_num_threads(1)

ATOMS = {"shoulder_l.abduct": 0.8, "elbow_r.flex": 0.9, "knee_l.flex": 0.6, "spine_02.twist": 0.15, "head.flex": 0.2}


@pytest.fixture(scope="module")
def person(model):
    """A posed, shaped BLSM body: its registration parameters and vertices."""
    g = torch.Generator().manual_seed(3)
    angles = torch.zeros(1, model.num_dofs)
    for name, value in ATOMS.items():
        angles[0, model.dof_names.index(name)] = value
    params = {
        "bone": 0.7 * torch.randn(1, model.num_bone_coeffs, generator=g),
        "shape": 0.7 * torch.randn(1, model.num_shape_coeffs, generator=g),
        "angles": angles,
        "global_orient": torch.tensor([[0.05, 0.5, -0.1]]),
        "transl": torch.tensor([[0.3, 0.95, -1.2]]),
    }
    with torch.no_grad():
        verts = model(**params).vertices[0].numpy()
    return {k: v[0].numpy() for k, v in params.items()}, verts


def write_textured_obj(folder, verts, model, texture, nan_vertex=None):
    """scan.obj with per-corner UVs (`f v/vt`), scan.mtl and scan.png."""
    folder.mkdir(parents=True, exist_ok=True)
    v = verts.astype(np.float64).copy()
    if nan_vertex is not None:
        v[nan_vertex] = np.nan
    f, fuv = model.faces.numpy() + 1, model.faces_uv.numpy() + 1
    lines = ["mtllib scan.mtl", "usemtl skin"]
    lines += [f"v {a:.7f} {b:.7f} {c:.7f}" for a, b, c in v]
    lines += [f"vt {a:.7f} {b:.7f}" for a, b in model.uvs.numpy()]
    lines += [f"f {a}/{ta} {b}/{tb} {c}/{tc}" for (a, b, c), (ta, tb, tc) in zip(f, fuv, strict=True)]
    (folder / "scan.obj").write_text("\n".join(lines) + "\n")
    (folder / "scan.mtl").write_text("newmtl skin\nKd 1 1 1\nmap_Kd scan.png\n")
    Image.fromarray(texture).save(folder / "scan.png")


def write_mesh(path, verts, faces, colours=None):
    import trimesh

    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".obj" and colours is None:  # plain `v` / `f`, BLSM vertex order kept
        lines = [f"v {a:.7f} {b:.7f} {c:.7f}" for a, b, c in verts] + [f"f {a} {b} {c}" for a, b, c in faces + 1]
        path.write_text("\n".join(lines) + "\n")
    else:
        trimesh.Trimesh(verts, faces, vertex_colors=colours, process=False).export(path)


def write_params(path, params, **override):
    path.parent.mkdir(parents=True, exist_ok=True)
    p = {**params, **override}
    if path.suffix == ".json":
        path.write_text(json.dumps({k: np.asarray(v).tolist() for k, v in p.items()}))
    else:
        np.savez(path, **p)


def position_colours(verts):
    lo, hi = verts.min(0), verts.max(0)
    c = np.clip((verts - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)
    return np.concatenate([c, np.full((len(c), 1), 255, np.uint8)], 1)


@pytest.fixture(scope="module")
def texture():
    t = np.zeros((64, 32, 3), np.uint8)
    t[..., 0] = np.arange(64)[:, None] * 4  # red grows downwards: row 0 = top = v 1
    t[..., 1] = np.arange(32)[None] * 8
    t[:8, :, 2] = 255
    return t


def rigged_back(subject, model):
    """The rigged subject posed in its registration's pose."""
    reg = subject.registration
    x = unconstrained_from_angles(torch.as_tensor(reg["angles"])[None], model.dof_limits)[0].numpy()
    params = {"pose": x, "global_orient": reg["global_orient"], "transl": reg["transl"]}
    return pose_subject(subject, model, params, "rigged")["vertices"]


def test_textured_obj_with_parameters(model, person, texture, tmp_path):
    params, verts = person
    folder = tmp_path / "scans" / "ada"
    write_textured_obj(folder, verts, model, texture)
    write_params(folder / "registration.json", params)

    s = import_scan(model, folder)
    assert s.id == "ada"
    # trimesh splits vertices at UV seams; the triangles and their corner UVs stay.
    np.testing.assert_allclose(s.vertices[s.faces], verts[model.faces.numpy()], atol=1e-6)
    np.testing.assert_allclose(s.uv[s.faces_uv], model.uvs.numpy()[model.faces_uv.numpy()], atol=1e-6)
    np.testing.assert_array_equal(s.texture, texture)
    assert s.meta["source"] == "scan" and s.meta["scan"] == str(folder / "scan.obj")
    assert s.meta["scan_sha256"] == blsm_io.sha256_file(folder / "scan.obj")
    assert s.meta["registration"]["source"] == "parameters"
    np.testing.assert_array_equal(s.registration["displacement"], 0)

    np.testing.assert_array_equal(pose_subject(s, model, {}, "raw")["vertices"], s.vertices)
    np.testing.assert_allclose(rigged_back(s, model), s.vertices, atol=1e-4)
    back = load_subject(save_subject(s, tmp_path / "ada.npz"))
    assert back.meta == json.loads(json.dumps(s.meta)) and back.texture.shape == texture.shape


def test_coloured_ply_with_fitted_mesh(model, person, tmp_path):
    params, verts = person
    folder = tmp_path / "bob"
    colours = position_colours(verts)
    write_mesh(folder / "scan.ply", verts, model.faces.numpy(), colours)
    # A registration mesh a little off the model's space: the fit gets close, displacements exact.
    target = verts + np.random.default_rng(0).normal(0, 0.0005, verts.shape)
    write_mesh(folder / "registration.obj", target, model.faces.numpy())

    s = import_scan(model, folder, texture_size=256)
    reg_meta = s.meta["registration"]
    assert reg_meta["source"] == "fitted mesh" and reg_meta["fit_mean_mm"] < 2.0
    assert reg_meta["sha256"] == blsm_io.sha256_file(folder / "registration.obj")
    np.testing.assert_allclose(registration_output(model, s.registration)[0].numpy(), target, atol=2e-5)
    np.testing.assert_allclose(s.registration["bone"], params["bone"], atol=0.05)
    np.testing.assert_allclose(s.registration["angles"], params["angles"], atol=0.03)
    np.testing.assert_allclose(rigged_back(s, model), verts, atol=1e-4)

    # Baked texture: every UV triangle's centre shows the mean colour of its corners.
    assert s.texture.shape == (256, 256, 3) and s.faces_uv.shape == s.faces.shape
    assert s.uv.min() >= 0 and s.uv.max() <= 1
    centre = s.uv[s.faces_uv].mean(1)
    row = np.clip(np.floor((1 - centre[:, 1]) * 256), 0, 255).astype(int)
    col = np.clip(np.floor(centre[:, 0] * 256), 0, 255).astype(int)
    diff = np.abs(s.texture[row, col].astype(float) - colours[:, :3][s.faces].mean(1))
    assert np.median(diff) < 2 and np.percentile(diff, 95) < 12


def test_textured_glb_and_npz_pose(model, person, texture, tmp_path):
    import trimesh

    params, verts = person
    write_textured_obj(tmp_path / "obj", verts, model, texture)
    obj = trimesh.load(tmp_path / "obj" / "scan.obj", force="mesh", process=False)
    (tmp_path / "cy").mkdir()
    obj.export(tmp_path / "cy" / "scan.glb")
    x = unconstrained_from_angles(torch.as_tensor(params["angles"])[None], model.dof_limits)[0].numpy()
    reg = {k: v for k, v in params.items() if k != "angles"}
    write_params(tmp_path / "cy" / "registration.npz", reg, pose=x, displacement=np.zeros((model.num_vertices, 3)))

    v, f, uv, fuv, tex = load_scan(tmp_path / "cy")
    np.testing.assert_array_equal(tex, texture)  # glTF's v-down UVs come back v up, row 0 on top
    np.testing.assert_allclose(uv[fuv], model.uvs.numpy()[model.faces_uv.numpy()], atol=1e-6)
    s = import_scan(model, tmp_path / "cy")
    np.testing.assert_allclose(s.registration["angles"], params["angles"], atol=1e-5)
    np.testing.assert_allclose(rigged_back(s, model), s.vertices, atol=1e-4)


# ------------------------------------------------------------------------------------------------
# Bad input: one-line ValueErrors that start with the offending file


def tiny(folder, faces, verts=None):
    """A small vertex-coloured PLY scan."""
    v = verts if verts is not None else np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1]], float)
    write_mesh(folder / "scan.ply", v, np.asarray(faces), position_colours(v + 1e-3))


def make_bad(kind, folder, model, person, texture):
    """Write a bad subject folder; return the path its error must start with."""
    params, verts = person
    faces = model.faces.numpy()
    good_obj = kind.startswith("reg")
    if good_obj:
        write_textured_obj(folder, verts, model, texture)
    if kind == "non_manifold_edge":  # a third face on the edge 0-1
        tiny(folder, [[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    elif kind == "non_manifold_vertex":  # two fans meeting at vertex 0
        tiny(folder, [[0, 1, 2], [0, 3, 4]], np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [-1, 0, 0], [-1, -1, 0]], float))
    elif kind == "degenerate_face":
        tiny(folder, [[0, 1, 2], [1, 3, 3]])
    elif kind == "unreadable":
        folder.mkdir(parents=True)
        (folder / "scan.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nend_header\n")
    elif kind == "missing_texture":
        write_textured_obj(folder, verts, model, texture)
        (folder / "scan.png").unlink()
        return folder / "scan.mtl"
    elif kind == "nan_vertex":
        write_textured_obj(folder, verts, model, texture, nan_vertex=10)
        return folder / "scan.obj"
    elif kind == "empty":
        folder.mkdir(parents=True)
        (folder / "scan.obj").write_text("# nothing\n")
        return folder / "scan.obj"
    elif kind == "no_colour":
        write_mesh(folder / "scan.obj", verts, faces)
        return folder / "scan.obj"
    elif kind == "two_scans":
        write_textured_obj(folder, verts, model, texture)
        tiny(folder, [[0, 1, 2]])
        return folder
    elif kind == "no_registration":
        write_textured_obj(folder, verts, model, texture)
        return folder
    elif kind == "reg_vertex_count":
        keep = (faces < model.num_vertices - 1).all(1)
        write_mesh(folder / "registration.obj", verts[:-1], faces[keep])
        return folder / "registration.obj"
    elif kind == "reg_param_size":
        write_params(folder / "registration.json", params, bone=np.zeros(model.num_bone_coeffs + 1))
        return folder / "registration.json"
    elif kind == "reg_nan":
        write_params(folder / "registration.npz", params, shape=np.full(model.num_shape_coeffs, np.nan))
        return folder / "registration.npz"
    elif kind == "reg_angle_limit":
        write_params(folder / "registration.json", params, angles=np.full(model.num_dofs, 5.0))
        return folder / "registration.json"
    return folder / "scan.ply"


BAD = [
    "non_manifold_edge", "non_manifold_vertex", "degenerate_face", "unreadable", "missing_texture", "nan_vertex",
    "empty", "no_colour", "two_scans", "no_registration", "reg_vertex_count", "reg_param_size", "reg_nan",
    "reg_angle_limit",
]  # fmt: skip


@pytest.mark.parametrize("kind", BAD)
def test_bad_input_names_the_file(kind, model, person, texture, tmp_path):
    folder = tmp_path / kind
    where = make_bad(kind, folder, model, person, texture)
    if not (folder / "registration.json").exists() and not kind.startswith("reg") and kind != "no_registration":
        write_params(folder / "registration.json", person[0])
    with pytest.raises(ValueError) as exc:
        import_scan(model, folder)
    msg = str(exc.value)
    assert msg.startswith(f"{where}: ") and "\n" not in msg, msg


def test_import_scans_skips_bad_folders(model, person, texture, tmp_path):
    root = tmp_path / "scans"
    write_textured_obj(root / "good", person[1], model, texture)
    write_params(root / "good" / "registration.json", person[0])
    bad = ["non_manifold_edge", "missing_texture", "reg_param_size"]
    where = {}
    for kind in bad:
        where[kind] = make_bad(kind, root / kind, model, person, texture)
        if not kind.startswith("reg"):
            write_params(root / kind / "registration.json", person[0])
    (root / ".cache").mkdir()  # hidden folders are not subjects

    with pytest.raises(ValueError, match=r"^" + str(root / "missing_texture")):
        import_scans(model, root)
    subjects, skipped = import_scans(model, root, skip_bad=True)
    assert [s.id for s in subjects] == ["good"]
    assert [name for name, _ in skipped] == sorted(bad)
    for name, reason in skipped:
        assert reason.startswith(f"{where[name]}: ")
    with pytest.raises(ValueError, match="no such scans folder"):
        import_scans(model, tmp_path / "nowhere")
    shutil.rmtree(root / "good")
