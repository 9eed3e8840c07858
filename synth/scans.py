"""Users' own scans as generator subjects: a folder per person, checked, registered and rigged.

Folder format::

  scans/
    <subject>/                  one folder per subject; the folder name is the subject id
      scan.obj | scan.ply | scan.glb   the scan mesh, metres, Y up, facing +Z (exactly one of these)
                                      with a texture (OBJ+MTL map_Kd, GLB baseColorTexture; UVs required)
                                      or per-vertex colours (PLY/OBJ/GLB)
      registration.json | registration.npz   its BLSM registration, either
          parameters: bone (Kb), shape (Ks), angles (47, radians) [or pose (47) unconstrained x],
                      global_orient (3), transl (3), and displacement (Vb, 3) (npz; optional, zero if absent)
      or registration.obj | registration.ply   a mesh in BLSM topology (same vertex count and faces as
          the model) in the scan's pose: its parameters are fitted on import

A scan with per-vertex colours gets a UV atlas (``xatlas``) and its colours baked into a texture, so
every subject has UVs and a texture. Scans may have holes; non-manifold edges (more than two faces)
or vertices (more than one fan of faces), degenerate faces, NaN or inf vertices, a texture file
named by the MTL or GLB that does not exist, and a registration that does not fit the model are
errors: one-line ``ValueError`` messages that start with the offending file's path.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm import io as blsm_io
from blsm.joint_limits import angles_from_unconstrained, unconstrained_from_angles
from blsm.kinematics import joint_rotations
from blsm.lbs import unskin
from blsm.model import BLSM
from synth.subjects import Subject, check_registration, rig_subject

SCAN_SUFFIXES = (".obj", ".ply", ".glb")
PARAM_SUFFIXES = (".json", ".npz")
MESH_SUFFIXES = (".obj", ".ply")
_PARAM_KEYS = ("bone", "shape", "angles", "pose", "global_orient", "transl", "displacement")


def _one(folder: Path, stem: str, suffixes: tuple[str, ...]) -> Path:
    """The single ``<stem><suffix>`` file of a subject folder."""
    found = [folder / f"{stem}{s}" for s in suffixes if (folder / f"{stem}{s}").is_file()]
    names = " | ".join(f"{stem}{s}" for s in suffixes)
    if not found:
        raise ValueError(f"{folder}: no {names} file")
    if len(found) > 1:
        raise ValueError(f"{folder}: more than one {stem} file ({', '.join(p.name for p in found)})")
    return found[0]


def _check_texture_files(path: Path) -> None:
    """Raise if the MTL or GLB names a texture file that does not exist (trimesh drops it silently)."""
    if path.suffix == ".obj":
        with open(path, errors="replace") as fh:
            libs = [n for line in fh if line.startswith("mtllib") for n in line.split()[1:]]
        for name in libs:
            mtl = path.parent / name
            if not mtl.is_file():
                raise ValueError(f"{path}: mtllib names {name}, which does not exist")
            for line in mtl.read_text(errors="replace").splitlines():
                words = line.split()
                if len(words) > 1 and words[0] == "map_Kd" and not (mtl.parent / words[-1]).is_file():
                    raise ValueError(f"{mtl}: map_Kd names {words[-1]}, which does not exist")
    elif path.suffix == ".glb":
        with open(path, "rb") as fh:
            head = fh.read(20)
            if len(head) < 20 or head[:4] != b"glTF" or head[16:20] != b"JSON":
                raise ValueError(f"{path}: not a binary glTF (.glb) file")
            (n,) = struct.unpack("<I", head[12:16])
            try:
                gltf = json.loads(fh.read(n))
            except (json.JSONDecodeError, UnicodeDecodeError) as exc:
                raise ValueError(f"{path}: unreadable glTF JSON chunk ({exc})") from None
        for image in gltf.get("images", []):
            uri = image.get("uri", "")
            if uri and not uri.startswith("data:") and not (path.parent / uri).is_file():
                raise ValueError(f"{path}: image {uri} does not exist")


def load_mesh(path: str | Path, keep_order: bool = False) -> Any:
    """Read a mesh file with trimesh (a GLB scene is concatenated) and check it.

    Args:
        path: an ``.obj``, ``.ply`` or ``.glb`` file.
        keep_order: keep an OBJ's vertex order (trimesh otherwise splits vertices at UV seams).

    Returns:
        A ``trimesh.Trimesh`` with finite vertices and manifold, non-degenerate faces.
    """
    import trimesh

    path = Path(path)
    _check_texture_files(path)
    kw = {"maintain_order": True} if keep_order and path.suffix == ".obj" else {}
    try:
        mesh = trimesh.load(path, force="mesh", process=False, **kw)
        if isinstance(mesh, trimesh.Scene):
            mesh = mesh.to_mesh()
    except Exception as exc:  # trimesh's parsers raise many kinds of errors on bad files
        raise ValueError(f"{path}: unreadable mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise ValueError(f"{path}: empty mesh (no triangles)")
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if not np.isfinite(v).all():
        raise ValueError(f"{path}: vertex {int(np.flatnonzero(~np.isfinite(v).all(1))[0])} is NaN or inf")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"{path}: faces index outside [0, {len(v)})")
    # Topology is checked on the welded mesh: loaders split vertices at UV seams (OBJ, GLB).
    _, first, inverse = np.unique(v, axis=0, return_index=True, return_inverse=True)
    f = first[inverse.ravel()][f]
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    bad = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2]) | (area <= 1e-14)
    if bad.any():
        raise ValueError(f"{path}: {int(bad.sum())} degenerate (zero-area) faces, e.g. {int(bad.argmax())}")
    edges, counts = np.unique(np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), 1), axis=0, return_counts=True)
    if (counts > 2).any():
        a, b = edges[counts.argmax()]
        raise ValueError(f"{path}: non-manifold: {int((counts > 2).sum())} edges in 3+ faces, e.g. {a}-{b}")
    nm = _non_manifold_vertices(f, len(v))
    if len(nm):
        raise ValueError(f"{path}: non-manifold: {len(nm)} vertices joining separate fans, e.g. {nm[0]}")
    return mesh


def _non_manifold_vertices(faces: np.ndarray, n: int) -> np.ndarray:
    """Vertices whose faces form more than one fan (bowties); holes (open fans) are fine."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    # Corner (v; a, b) joins the link nodes (v, a) and (v, b); one fan = one connected link.
    v = faces.ravel().astype(np.int64)
    a, b = np.roll(faces, -1, 1).ravel(), np.roll(faces, -2, 1).ravel()
    nodes, inv = np.unique(np.concatenate([v * n + a, v * n + b]), return_inverse=True)
    k = len(v)
    graph = coo_matrix((np.ones(k), (inv[:k], inv[k:])), shape=(len(nodes), len(nodes)))
    ncomp, label = connected_components(graph, directed=False)
    owner = np.zeros(ncomp, np.int64)
    owner[label] = nodes // n
    return np.flatnonzero(np.bincount(owner, minlength=n) > 1)


def bake_vertex_colours(
    vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray, size: int = 1024
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A UV atlas (xatlas) and a texture with the vertex colours baked into it.

    Args:
        vertices: (V, 3); faces: (F, 3); colours: (V, 3) uint8 sRGB.
        size: texture size in texels.

    Returns:
        uv (U, 2) (v up), faces_uv (F, 3) (face order kept) and texture (size, size, 3) uint8, row 0
        at v = 1; texels outside every chart take the colour of the nearest texel inside one.
    """
    import xatlas
    from scipy import ndimage

    from synth.raster import rasterise_uv

    vmap, faces_uv, uv = xatlas.parametrize(np.asarray(vertices, np.float32), np.asarray(faces, np.uint32))
    faces_uv = faces_uv.astype(np.int64)
    corner = np.asarray(colours, np.float64)[vmap][faces_uv]  # (F, 3, 3) colour of each face corner
    texels, face, bary = rasterise_uv(uv, faces_uv, size)
    image = np.zeros((size * size, 3))
    image[texels] = np.einsum("nk,nkc->nc", bary, corner[face])
    empty = np.ones(size * size, bool)
    empty[texels] = False
    # Dilation: every texel outside the charts copies its nearest inside texel, so that bilinear
    # lookups and mip-maps near chart borders do not bleed the background in.
    _, (iy, ix) = ndimage.distance_transform_edt(empty.reshape(size, size), return_indices=True)
    image = image.reshape(size, size, 3)[iy, ix]
    return uv.astype(np.float32), faces_uv, np.clip(np.rint(image), 0, 255).astype(np.uint8)


def load_scan(
    folder: str | Path, texture_size: int = 1024
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Read and check a subject folder's scan (or a scan file).

    Args:
        folder: the subject folder (or the scan file itself).
        texture_size: texture size in texels when vertex colours are baked.

    Returns:
        vertices (V, 3) metres, faces (F, 3), uv (U, 2) v up, faces_uv (F, 3), texture (H, W, 3) uint8
        sRGB with row 0 at v = 1 (trimesh's convention for both OBJ and GLB).
    """
    folder = Path(folder)
    path = folder if folder.is_file() else _one(folder, "scan", SCAN_SUFFIXES)
    mesh = load_mesh(path)
    v, f = np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int64)
    visual = mesh.visual
    uv = getattr(visual, "uv", None)
    mat = getattr(visual, "material", None)
    image = getattr(mat, "image", None)
    image = getattr(mat, "baseColorTexture", None) if image is None else image
    if uv is not None and image is not None:
        uv = np.asarray(uv, np.float32)
        if uv.shape != (len(v), 2) or not np.isfinite(uv).all():
            raise ValueError(f"{path}: UVs must be finite, one per vertex, got {uv.shape} for {len(v)}")
        return v, f, uv, f.copy(), np.asarray(image.convert("RGB"), np.uint8)
    if getattr(visual, "kind", None) == "vertex":
        colours = np.asarray(visual.vertex_colors)[:, :3]
        uv, faces_uv, texture = bake_vertex_colours(v, f, colours, texture_size)
        return v, f, uv, faces_uv, texture
    if image is not None:
        raise ValueError(f"{path}: has a texture but no UVs")
    raise ValueError(f"{path}: no texture or vertex colours (a textured mesh with UVs, or vertex colours)")


# ------------------------------------------------------------------------------------------------
# Registration


def _read_parameters(model: BLSM, path: Path) -> dict[str, np.ndarray]:
    if path.suffix == ".json":
        try:
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: unreadable registration JSON ({exc})") from None
        if not isinstance(data, dict):
            raise ValueError(f"{path}: registration JSON must be an object of parameter arrays")
    else:
        data = blsm_io.read_npz(path, "registration")
    unknown = sorted(set(data) - set(_PARAM_KEYS))
    if unknown:
        raise ValueError(f"{path}: unknown registration keys {unknown} (known: {', '.join(_PARAM_KEYS)})")
    if ("pose" in data) == ("angles" in data):
        raise ValueError(f"{path}: give exactly one of angles (radians) or pose (unconstrained x)")
    try:
        reg = {k: np.asarray(val, dtype=np.float32) for k, val in data.items()}
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: registration values must be numeric arrays ({exc})") from None
    reg.setdefault("displacement", np.zeros((model.num_vertices, 3), np.float32))
    lim = model.dof_limits.numpy()
    if "pose" in reg:
        x = reg.pop("pose")
        if x.shape != (model.num_dofs,):
            raise ValueError(f"{path}: registration 'pose' has shape {x.shape}, the model needs (47,)")
        reg["angles"] = angles_from_unconstrained(torch.as_tensor(x)[None], model.dof_limits)[0].numpy()
    check_registration(model, reg, str(path))
    a = reg["angles"]
    out = (a < lim[:, 0] - 1e-5) | (a > lim[:, 1] + 1e-5)
    if out.any():
        i = int(out.argmax())
        raise ValueError(f"{path}: angle {model.dof_names[i]} = {a[i]:.4f} rad is outside {lim[i].round(4)}")
    reg["angles"] = np.clip(a, lim[:, 0], lim[:, 1]).astype(np.float32)
    return reg


def _initial_pose(model: BLSM, target: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Global orientation (1, 3) and pose x (1, 47) from the rotation of each bone's rigid core."""
    from scipy.spatial.transform import Rotation

    rest, w = model.template.double().numpy(), model.weights.double().numpy()
    rots = []
    for j in range(model.num_joints):  # Kabsch of the vertices bone j dominates, rest -> target
        sel = np.flatnonzero(w[:, j] > 0.5) if (w[:, j] > 0.5).sum() >= 10 else np.argsort(-w[:, j])[:30]
        a, b = target[sel] - target[sel].mean(0), rest[sel] - rest[sel].mean(0)
        rots.append(Rotation.align_vectors(a, b)[0].as_matrix())
    g, q = np.stack(rots), model.frames.double().numpy()
    # World rotations chain as G_j = G_parent Q_j R_j Q_j^T (blsm.kinematics): R_j = Q^T G_p^T G_j Q.
    local = [np.eye(3) if p < 0 else q[j].T @ g[p].T @ g[j] @ q[j] for j, p in enumerate(model.parents)]
    goal = torch.as_tensor(np.stack(local), dtype=torch.float32)[None]
    lim = model.dof_limits.float()
    # Start near the rest pose but off the limits, where tanh would have no gradient.
    x = unconstrained_from_angles(torch.zeros(1, model.num_dofs), lim, eps=0.1).requires_grad_(True)
    opt = torch.optim.Adam([x], lr=0.1)
    for _ in range(200):
        opt.zero_grad()
        theta = angles_from_unconstrained(x, lim)
        rot = joint_rotations(theta, model.dof_slots, model.dof_axis, model.dof_sign)
        ((rot - goal) ** 2).sum().backward()
        opt.step()
        with torch.no_grad():  # keep tanh off saturation, so that the mesh fit can still move it
            x.clamp_(-3.0, 3.0)
    orient = Rotation.from_matrix(g[model.parents.index(-1)]).as_rotvec()
    return torch.tensor(orient, dtype=torch.float32)[None], x.detach()


def fit_posed_registration(
    model: BLSM, target: np.ndarray, iterations: int = 40
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Fit BLSM to a posed body in its topology, then set displacements that reproduce it exactly.

    Staged: (1) the rotation of each bone's rigid core (Kabsch) gives ``global_orient`` and, by an
    Adam fit of the joint rotations in the unconstrained x of Eq. 6, the angles; ``transl`` matches
    the centroids; (2) bounded nonlinear least squares (``scipy.optimize.least_squares``, trust
    region reflective, float64) on the vertex distances over all of ``global_orient``, ``transl``,
    the angles (inside their limits), bone and shape coefficients, with a forward-difference
    Jacobian from one batched model pass. (Adam on the vertex distances from the rest pose, or pose before shape, stops in
    local minima millimetres off; so does Gauss-Newton in x, whose atoms saturate at a limit.) The
    displacements are then ``D_i = A_i^-1 (target_i - b_i) - T_i`` with the blended transform of
    vertex i, as in :func:`synth.subjects.fit_registration`.

    Args:
        target: (Vb, 3) posed body in the model's topology, metres.
        iterations: residual evaluations of the least-squares solve at most.

    Returns:
        The registration (``angles`` in radians) and a report: ``fit_mean_mm`` and ``fit_max_mm``
        (vertex error before displacements).
    """
    import copy

    from scipy.optimize import least_squares

    goal = np.asarray(target, np.float64)
    orient, x = _initial_pose(model, goal)
    m64 = copy.deepcopy(model).double()
    with torch.no_grad():
        angles = angles_from_unconstrained(x.double(), m64.dof_limits)
        posed = m64(angles=angles, global_orient=orient.double()).vertices[0]
        transl = torch.as_tensor(goal.mean(0)) - posed.mean(0)
    sizes = {"global_orient": 3, "transl": 3, "angles": model.num_dofs}
    sizes.update(bone=model.num_bone_coeffs, shape=model.num_shape_coeffs)
    nb = sizes["bone"] + sizes["shape"]
    start = torch.cat([orient[0].double(), transl, angles[0], torch.zeros(nb, dtype=torch.float64)])
    limits = m64.dof_limits.numpy()
    lo = np.concatenate([np.full(6, -np.inf), limits[:, 0], np.full(nb, -np.inf)])
    hi = np.concatenate([np.full(6, np.inf), limits[:, 1], np.full(nb, np.inf)])

    def unpack(t: torch.Tensor) -> dict[str, torch.Tensor]:
        return dict(zip(sizes, torch.split(t, list(sizes.values()), dim=1), strict=True))

    def vertices(t: torch.Tensor) -> torch.Tensor:  # (B, P) parameters -> (B, 3 Vb)
        return m64(**unpack(t)).vertices.reshape(len(t), -1)

    flat = goal.ravel()

    @torch.no_grad()
    def residual(t: np.ndarray) -> np.ndarray:
        return vertices(torch.from_numpy(t)[None])[0].numpy() - flat

    @torch.no_grad()
    def jacobian(t: np.ndarray) -> np.ndarray:  # (3 Vb, P), every column from one batched pass
        h = np.where(t + 1e-6 <= hi, 1e-6, -1e-6)  # step into the box
        fx = vertices(torch.from_numpy(np.concatenate([t[None], t + np.diag(h)]))).numpy()
        return ((fx[1:] - fx[0]) / h[:, None]).T

    fit = least_squares(residual, start.numpy(), jac=jacobian, bounds=(lo, hi), method="trf", max_nfev=iterations)
    with torch.no_grad():
        p = {k: v.float() for k, v in unpack(torch.from_numpy(fit.x)[None]).items()}
        out = model(**p)
        err = np.linalg.norm(out.vertices[0].numpy() - goal, axis=1) * 1000.0
        rest = unskin(torch.as_tensor(goal), model.weights.double(), out.skinning_transforms[0].double())
        disp = rest.numpy() - out.template[0].numpy()
    reg = {k: p[k][0].numpy() for k in ("bone", "shape", "global_orient", "transl")}
    reg.update(angles=out.angles[0].numpy(), displacement=disp)
    report = {"fit_mean_mm": float(err.mean()), "fit_max_mm": float(err.max())}
    return {k: np.asarray(val, dtype=np.float32) for k, val in reg.items()}, report


def load_registration(model: BLSM, folder: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """A subject folder's registration (or a registration file): parameters, or fitted to a mesh.

    Returns:
        The registration (``bone``, ``shape``, ``angles`` radians, ``global_orient``, ``transl``,
        ``displacement``) and its meta: ``source`` ("parameters" or "fitted mesh"), ``file``,
        ``sha256`` and, for a fitted mesh, the fit report (``fit_mean_mm``: before displacements).
    """
    folder = Path(folder)
    path = folder if folder.is_file() else _one(folder, "registration", PARAM_SUFFIXES + MESH_SUFFIXES)
    meta: dict[str, Any] = {"file": str(path), "sha256": blsm_io.sha256_file(path)}
    if path.suffix in PARAM_SUFFIXES:
        return _read_parameters(model, path), {"source": "parameters", **meta}
    mesh = load_mesh(path, keep_order=True)
    if len(mesh.vertices) != model.num_vertices:
        raise ValueError(
            f"{path}: {len(mesh.vertices)} vertices, the model has {model.num_vertices} "
            "(a registration mesh must be in BLSM topology)"
        )
    if not np.array_equal(np.asarray(mesh.faces), model.faces.numpy()):
        raise ValueError(f"{path}: faces differ from the model's (a registration mesh is in BLSM topology)")
    try:
        reg, report = fit_posed_registration(model, np.asarray(mesh.vertices))
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    check_registration(model, reg, str(path))
    return reg, {"source": "fitted mesh", **meta, **report}


# ------------------------------------------------------------------------------------------------
# Import


def import_scan(model: BLSM, folder: str | Path, texture_size: int = 1024) -> Subject:
    """A subject from a scan folder (see the module docstring): checked, registered and rigged.

    Args:
        model: the BLSM model the registration belongs to.
        folder: the subject folder; its name is the subject id.
        texture_size: texture size in texels when vertex colours are baked.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: no such scan folder")
    scan = _one(folder, "scan", SCAN_SUFFIXES)
    vertices, faces, uv, faces_uv, texture = load_scan(scan, texture_size)
    reg, reg_meta = load_registration(model, folder)
    meta = {"source": "scan", "scan": str(scan), "scan_sha256": blsm_io.sha256_file(scan)}
    meta["registration"] = reg_meta
    return rig_subject(model, folder.name, vertices, faces, uv, faces_uv, texture, reg, meta)


def check_scan(model: BLSM, folder: str | Path) -> None:
    """Open and check a subject folder's files without the slow work of :func:`import_scan` (no
    fitting, baking or rigging): the scan mesh and its texture or colours, the registration file
    (parameters read and checked; a registration mesh loaded and its topology checked)."""
    folder = Path(folder)
    scan = _one(folder, "scan", SCAN_SUFFIXES)
    mesh = load_mesh(scan)
    visual = mesh.visual
    mat = getattr(visual, "material", None)
    image = getattr(mat, "image", None)
    image = getattr(mat, "baseColorTexture", None) if image is None else image
    has_uv = getattr(visual, "uv", None) is not None
    if not (has_uv and image is not None) and getattr(visual, "kind", None) != "vertex":
        if image is not None:
            raise ValueError(f"{scan}: has a texture but no UVs")
        raise ValueError(f"{scan}: no texture or vertex colours (a textured mesh with UVs, or vertex colours)")
    path = _one(folder, "registration", PARAM_SUFFIXES + MESH_SUFFIXES)
    if path.suffix in PARAM_SUFFIXES:
        _read_parameters(model, path)
        return
    reg = load_mesh(path, keep_order=True)
    if len(reg.vertices) != model.num_vertices or not np.array_equal(np.asarray(reg.faces), model.faces.numpy()):
        raise ValueError(f"{path}: not in BLSM topology ({len(reg.vertices)} vertices, the model has {model.num_vertices})")


def subject_folders(root: Path) -> list[Path]:
    """The subject folders under ``root``, sorted by name (hidden ones ignored); a ValueError naming
    ``root`` when it is missing or holds none."""
    if not root.is_dir():
        raise ValueError(f"{root}: no such scans folder")
    folders = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not folders:
        raise ValueError(f"{root}: no subject folders")
    return folders


def check_scans(model: BLSM, root: str | Path, skip_bad: bool = False) -> list[tuple[str, str]]:
    """:func:`check_scan` on every subject folder under ``root``, before any work starts.

    Returns:
        The bad folders as (name, reason) pairs with ``skip_bad`` (an error when every folder is
        bad); without it the first bad folder raises its ValueError.
    """
    root = Path(root)
    folders = subject_folders(root)
    bad = []
    for folder in folders:
        try:
            check_scan(model, folder)
        except ValueError as exc:
            if not skip_bad:
                raise
            bad.append((folder.name, str(exc)))
    if len(bad) == len(folders):
        raise ValueError(f"{root}: no usable scan ({bad[0][1]})")
    return bad


def import_scans(
    model: BLSM, root: str | Path, skip_bad: bool = False, texture_size: int = 1024
) -> tuple[list[Subject], list[tuple[str, str]]]:
    """All subject folders under ``root`` (sorted by name; hidden folders are ignored).

    Args:
        skip_bad: list a folder whose import fails instead of raising.

    Returns:
        The subjects and the skipped folders as (name, reason) pairs.
    """
    root = Path(root)
    folders = subject_folders(root)
    subjects, skipped = [], []
    for folder in folders:
        try:
            subjects.append(import_scan(model, folder, texture_size))
        except ValueError as exc:
            if not skip_bad:
                raise
            skipped.append((folder.name, str(exc)))
    return subjects, skipped
