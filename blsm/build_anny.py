"""Build the first BLSM from the Anny body model (``blsm build-anny``).

Anny (PyPI ``anny``, Apache-2.0 code, CC0 MakeHuman assets) stands in for scanned people. The
steps follow paper 000 Sec. 4 (thesis Sec. 5.4) where Anny makes them simpler:

1. Template: the mean rest shape of a sampled population, cut at the sagittal plane, the left half
   decimated with its cut border fixed (quadric edge collapse, ``pyfqmr``), mirrored and welded, so
   the mesh is closed, manifold and exactly left/right symmetric with a known vertex mirror map.
   Every population body is carried onto it by the barycentric coordinates of each template vertex
   on the original Anny surface (the registrations are in correspondence by construction).
2. Skeleton: 20 BLSM bones chosen from Anny's 104-bone rig (fingers, toes and eyes folded into hand,
   foot and head); LBS weights summed over the folded Anny bones and transferred the same way.
3. Bone-length PCA (Sec. 4.2): bone lengths over the population, divided by their mean, so
   ``b_mean = 1``; the basis is scaled to one standard deviation per coefficient.
4. First bone-corrective blendshapes (Eq. 7) and shape PCA (Eq. 8): every body is un-skinned with
   its bone scales at zero pose (inverse of the blended Eq. 12 transforms); the correctives are the
   ridge regression of the un-skinned offsets on the bone coefficients and the shape basis is the
   PCA of what remains. The scan-fitting pipeline (Eqs. 13-15) will replace these estimates.
"""

from __future__ import annotations

import datetime
import json
import math
import sys
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from blsm import io, skeleton
from blsm.joint_limits import DEFAULT_DOF_TABLE, load_dof_table
from blsm.kinematics import forward_kinematics, local_scales
from blsm.lbs import linear_blend_skinning, unskin

# Anny bones folded into each BLSM bone; the first one gives the BLSM bone's head.
ANNY_BONES: dict[str, tuple[str, ...]] = {
    "pelvis": ("root", "pelvis.L", "pelvis.R", "spine05"),
    "spine_01": ("spine04", "spine03"),
    "spine_02": ("spine02",),
    "spine_03": ("spine01",),
    "neck": ("neck01", "neck02", "neck03"),
    "head": ("head", "eye.L", "eye.R"),
    "clavicle_l": ("clavicle.L", "shoulder01.L"),
    "shoulder_l": ("upperarm01.L", "upperarm02.L"),
    "elbow_l": ("lowerarm01.L", "lowerarm02.L"),
    "wrist_l": ("wrist.L", "finger*.L", "metacarpal*.L"),
    "hip_l": ("upperleg01.L", "upperleg02.L"),
    "knee_l": ("lowerleg01.L", "lowerleg02.L"),
    "ankle_l": ("foot.L", "toe*.L"),
}
for _name in list(ANNY_BONES):
    if _name.endswith("_l"):
        ANNY_BONES[_name[:-2] + "_r"] = tuple(b.replace(".L", ".R") for b in ANNY_BONES[_name])

COCO17 = (
    "nose", "left_eye", "right_eye", "left_ear", "right_ear",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
)  # fmt: skip
# COCO body keypoints are the BLSM joints; face keypoints are surface points.
COCO_JOINT = {
    "shoulder": "shoulder", "elbow": "elbow", "wrist": "wrist",
    "hip": "hip", "knee": "knee", "ankle": "ankle",
}  # fmt: skip
FACE_COCO = ("nose", "left_eye", "right_eye", "left_ear", "right_ear")
EXTRA_SURFACE = ("head_top", "hand_tip_l", "hand_tip_r", "toe_tip_l", "toe_tip_r", "heel_l", "heel_r")

ANNY_TO_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""Anny is Z up and faces -Y; BLSM is Y up and faces +Z: (x, y, z) -> (x, z, -y)."""


def _log(msg: str) -> None:
    print(f"[build-anny] {msg}", file=sys.stderr, flush=True)


def _match(pattern: str, name: str) -> bool:
    if pattern.endswith(".L") or pattern.endswith(".R"):
        stem, side = pattern[:-2], pattern[-2:]
        if not name.endswith(side):
            return False
        pattern, name = stem, name[:-2]
    if "*" in pattern:
        return name.startswith(pattern.split("*")[0])
    return pattern == name


def anny_bone_groups(labels: list[str]) -> list[list[int]]:
    """Anny bone indices folded into each BLSM bone, in BLSM bone order; every Anny bone once."""
    groups = []
    for name in skeleton.BONE_NAMES:
        groups.append([i for i, lab in enumerate(labels) if any(_match(p, lab) for p in ANNY_BONES[name])])
    used = sorted(i for g in groups for i in g)
    if used != list(range(len(labels))):
        missing = set(range(len(labels))) - set(used)
        raise RuntimeError(f"Anny bones not mapped exactly once: {[labels[i] for i in missing]}")
    return groups


def symmetric_half_decimation(vertices: np.ndarray, faces: np.ndarray, half_faces: int):
    """Decimate a symmetric closed mesh into a symmetric closed mesh with a vertex mirror map.

    Args:
        vertices: (V, 3) mesh symmetric about x = 0.
        faces: (F, 3) triangles.
        half_faces: number of triangles to keep in the left half.

    Returns:
        (vertices (V', 3), faces (F', 3), mirror (V',)) of the decimated mesh.
    """
    import pyfqmr
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    half = trimesh.intersections.slice_mesh_plane(mesh, plane_normal=[1, 0, 0], plane_origin=[0, 0, 0], cap=False)
    half.merge_vertices()
    simp = pyfqmr.Simplify()
    simp.setMesh(np.asarray(half.vertices), np.asarray(half.faces))
    simp.simplify_mesh(target_count=half_faces, aggressiveness=7, preserve_border=True, verbose=0)
    hv, hf, _ = simp.getMesh()
    hv = hv.astype(np.float64)
    on_plane = np.abs(hv[:, 0]) < 1e-7
    hv[on_plane, 0] = 0.0
    n = len(hv)
    off = np.flatnonzero(~on_plane)
    right_index = np.arange(n)
    right_index[off] = n + np.arange(len(off))
    rv = hv[off] * np.array([-1.0, 1.0, 1.0])
    verts = np.concatenate([hv, rv])
    faces_r = right_index[hf][:, ::-1]  # a reflection flips the winding
    faces_all = np.concatenate([hf, faces_r]).astype(np.int64)
    mirror = np.arange(len(verts))
    mirror[off] = n + np.arange(len(off))
    mirror[n + np.arange(len(off))] = off
    out = trimesh.Trimesh(verts, faces_all, process=False)
    if not (out.is_watertight and out.is_winding_consistent):
        raise RuntimeError("symmetric decimation did not give a closed, consistently wound mesh")
    return verts, faces_all, mirror


def barycentric_embedding(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray):
    """Closest point on a mesh for each query point, as (face index (P,), barycentric (P, 3))."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    closest, _, tri = trimesh.proximity.closest_point(mesh, points)
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], closest)
    bary = np.clip(bary, 0.0, None)
    bary /= bary.sum(1, keepdims=True)
    return tri, bary


def barycentric_interpolate(
    values: np.ndarray, faces: np.ndarray, tri: np.ndarray, bary: np.ndarray
) -> np.ndarray:
    """Barycentric interpolation of per-vertex values at points embedded in a mesh.

    Args:
        values: (..., V, C) per-vertex values (e.g. positions in metres).
        faces: (F, 3) faces of the mesh the points are embedded in.
        tri: (P,) face of each point, from :func:`barycentric_embedding`.
        bary: (P, 3) barycentric coordinates of each point in its face.

    Returns:
        (..., P, C) the values at the points.
    """
    corner = faces[tri]  # (P, 3)
    return np.einsum("...pkc,pk->...pc", values[..., corner, :], bary)


def _scaled_chain(b: np.ndarray, heads: np.ndarray, frames: np.ndarray):
    """Skinning transforms (linear (N, J, 3, 3), offset (N, J, 3)) at zero pose for bone scales b
    (N, J): Eqs. 3 and 5 through :mod:`blsm.kinematics`, in float64."""
    bt = torch.as_tensor(b, dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64).expand(*bt.shape, 3, 3)
    s = local_scales(bt, torch.as_tensor(skeleton.BONE_PARENTS))
    lin, off, _ = forward_kinematics(
        eye, s, torch.as_tensor(heads), torch.as_tensor(frames), list(skeleton.BONE_PARENTS)
    )
    return lin, off


_FLIP = np.array([-1.0, 1.0, 1.0])


@dataclass
class _AnnyPopulation:
    """Anny bodies in BLSM axes, symmetrised, each relative to its root joint (moved to the mean root).

    Attributes:
        verts: (N, Va, 3) rest vertices, metres. faces: (Fa, 3) Anny's triangles.
        joints: (N, J, 3) BLSM joints (the head of each BLSM bone's first Anny bone).
        coco: (N, 5, 3) Anny's COCO face keypoints.
        bone_weights: (Va, J) Anny's skinning weights summed per BLSM bone.
        version: the ``anny`` package version.
    """

    verts: np.ndarray
    faces: np.ndarray
    joints: np.ndarray
    coco: np.ndarray
    bone_weights: np.ndarray
    version: str


def _anny_population(n_bodies: int, seed: int) -> _AnnyPopulation:
    """``n_bodies`` Anny phenotypes drawn uniformly with ``seed``."""
    import anny
    from anny.skinning.skinning import apply_linear_blendshape
    from anny.utils.mesh_utils import get_symmetric_vertex_indices

    t0 = time.time()
    model = anny.Anny(topology="anny-noeyes-notongue")
    full = anny.Anny(topology="anny")  # with eyes, for Anny's COCO face keypoints
    _log(f"Anny {anny.__version__} loaded in {time.time() - t0:.0f} s")

    gen = torch.Generator().manual_seed(seed)
    pheno = torch.rand(n_bodies, len(model.phenotype_labels), generator=gen, dtype=torch.float64)
    kw = {lab: pheno[:, i] for i, lab in enumerate(model.phenotype_labels)}
    with torch.no_grad():
        coeffs = model.get_phenotype_blendshape_coefficients(**kw)
        verts = model.get_rest_vertices(coeffs).numpy() @ ANNY_TO_WORLD.T  # (N, Va, 3)
        heads = apply_linear_blendshape(model.template_bone_heads, model.bone_heads_blendshapes, coeffs)
        heads = heads.numpy() @ ANNY_TO_WORLD.T  # (N, 104, 3)
        coeffs_full = full.get_phenotype_blendshape_coefficients(**kw)
        full_verts = full.get_rest_vertices(coeffs_full)
        regressor = anny.KeypointsRegressor.coco(full, labels=[n for n in COCO17 if n in FACE_COCO])
        coco = regressor(dict(vertices=full_verts)).numpy() @ ANNY_TO_WORLD.T  # (N, 5, 3)
    labels = list(model.bone_labels)

    # Symmetrise every body (Anny's vertex mirror map, bone names mirrored).
    sym = get_symmetric_vertex_indices(model.template_vertices, axis=0, threshold=1e-4).numpy()
    verts = 0.5 * (verts + verts[:, sym] * _FLIP)
    bone_sym = [labels.index(lab.replace(".L", ".X").replace(".R", ".L").replace(".X", ".R")) for lab in labels]
    heads = 0.5 * (heads + heads[:, bone_sym] * _FLIP)

    groups = anny_bone_groups(labels)
    joints = heads[:, [g[0] for g in groups]]  # (N, J, 3)
    # Express every body relative to its root joint (at the population's mean root), as BLSM keeps
    # the root fixed while bones scale; otherwise the correctives would have to carry the body's
    # translation (a child's pelvis is lower than an adult's).
    shift = joints[:, :1] - joints[:, :1].mean(0, keepdims=True)  # (N, 1, 3)

    # Anny's sparse weights summed per BLSM bone.
    n_va = verts.shape[1]
    wa = np.zeros((n_va, len(labels)))
    rows = np.arange(n_va)[:, None]
    np.add.at(wa, (rows, model.vertex_bone_indices.numpy()), model.vertex_bone_weights.numpy())
    wb = np.stack([wa[:, g].sum(1) for g in groups], axis=1)  # (Va, J)
    faces = model.faces.numpy()
    return _AnnyPopulation(verts - shift, faces, joints - shift, coco - shift, wb, anny.__version__)


def _transfer_weights(
    pop: _AnnyPopulation, tri: np.ndarray, bary: np.ndarray, mirror: np.ndarray
) -> np.ndarray:
    """(V, J) the per-bone Anny weights carried onto the template, symmetric, pruned below 1e-4."""
    weights = barycentric_interpolate(pop.bone_weights, pop.faces, tri, bary)
    bone_mirror = [skeleton.BONE_NAMES.index(skeleton.mirror_name(n)) for n in skeleton.BONE_NAMES]
    weights = 0.5 * (weights + weights[mirror][:, bone_mirror])
    weights = np.clip(weights, 0.0, None)
    weights[weights < 1e-4] = 0.0
    weights /= weights.sum(1, keepdims=True)
    return weights


def _leaf_tips(template: np.ndarray, vertex_bones: np.ndarray, joints: np.ndarray,
               mirror: np.ndarray) -> dict[str, int]:
    """Template vertices of the head top, middle fingertip, toe tip and heel (left, mirrored right);
    ``joints`` (J, 3) are the mean joints."""
    bi = skeleton.BONE_NAMES.index

    def region(bone: str) -> np.ndarray:
        return np.flatnonzero(vertex_bones == bi(bone))

    head_region = region("head")
    tips = {"head_top": head_region[np.argmax(template[head_region, 1])]}
    hand = region("wrist_l")
    tips["hand_tip_l"] = hand[np.argmax(np.linalg.norm(template[hand] - joints[bi("wrist_l")], axis=1))]
    foot = region("ankle_l")
    tips["toe_tip_l"] = foot[np.argmax(template[foot, 2])]
    low = foot[template[foot, 1] < template[foot, 1].min() + 0.02]
    tips["heel_l"] = low[np.argmin(template[low, 2])]
    for k in ("hand_tip", "toe_tip", "heel"):
        tips[f"{k}_r"] = mirror[tips[f"{k}_l"]]
    return tips


def _bone_lengths(joints: np.ndarray, verts: np.ndarray, tips: dict[str, int]) -> np.ndarray:
    """RMS distance from each head to its children's heads (or to the leaf tip): (N, J)."""
    out = []
    for j, name in enumerate(skeleton.BONE_NAMES):
        children = [c for c, p in enumerate(skeleton.BONE_PARENTS) if p == j]
        if children:
            d = joints[:, children] - joints[:, j : j + 1]
        else:
            d = verts[:, tips[skeleton.LEAF_TIPS[name]]][:, None] - joints[:, j : j + 1]
        out.append(np.sqrt((d**2).sum(-1).mean(-1)))
    return np.stack(out, axis=1)


def _bind_skeleton(
    heads: np.ndarray, template: np.ndarray, tips: dict[str, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Tails (J, 3) of the bones with heads ``heads`` (a child's head or a leaf tip) and the bind
    frames (J, 3, 3) from heads and tails."""
    tails = np.zeros_like(heads)
    for j, name in enumerate(skeleton.BONE_NAMES):
        if name in skeleton.LEAF_TIPS:
            tails[j] = template[tips[skeleton.LEAF_TIPS[name]]]
        else:
            tails[j] = heads[skeleton.BONE_NAMES.index(skeleton.PRIMARY_CHILD[name])]
    return tails, skeleton.bind_frames(heads, tails)


def _keypoints(template: np.ndarray, faces: np.ndarray, tips: dict[str, int], coco_mean: np.ndarray):
    """Keypoints: BLSM joints, tips, COCO-17 (face ones from Anny's regressor, body ones = joints).

    Returns:
        (names, joint index (K,) or -1, surface vertices (K, 3), barycentric weights (K, 3)).
    """
    bi = skeleton.BONE_NAMES.index
    kp_names: list[str] = list(skeleton.BONE_NAMES) + list(EXTRA_SURFACE) + list(COCO17)
    kp_joint = np.full(len(kp_names), -1)
    kp_vert = np.zeros((len(kp_names), 3), dtype=np.int64)
    kp_w = np.zeros((len(kp_names), 3))
    for k, name in enumerate(kp_names):
        if name in skeleton.BONE_NAMES:
            kp_joint[k] = bi(name)
        elif name in tips:
            kp_vert[k] = tips[name]
            kp_w[k] = (1.0, 0.0, 0.0)
        else:
            side, _, part = name.partition("_")
            if part in COCO_JOINT:
                kp_joint[k] = bi(f"{COCO_JOINT[part]}_{side[0]}")
            else:
                src = coco_mean[FACE_COCO.index(name)]
                ftri, fb = barycentric_embedding(template, faces, src[None])
                kp_vert[k] = faces[ftri[0]]
                kp_w[k] = fb[0]
    return kp_names, kp_joint, kp_vert, kp_w


def _rest_flexion(heads: np.ndarray, tails: np.ndarray, frames: np.ndarray) -> dict[str, float]:
    """Signed rest flexion (degrees) of the left knee and elbow about the joint's x axis, from the
    parent's direction."""
    rest = {}
    for name in ("knee_l", "elbow_l"):
        j = skeleton.BONE_NAMES.index(name)
        p = skeleton.BONE_PARENTS[j]
        up = heads[j] - heads[p]
        down = tails[j] - heads[j]
        ang = math.atan2(np.dot(np.cross(up, down), frames[j][:, 0]), np.dot(up, down))
        rest[name] = math.degrees(ang)
    return rest


def _symmetric_basis(basis: np.ndarray, mirror: np.ndarray) -> np.ndarray:
    """(K, 3V) vertex offsets averaged with their mirror images (exactly symmetric)."""
    bb = basis.reshape(len(basis), -1, 3)
    return (0.5 * (bb + bb[:, mirror] * _FLIP)).reshape(basis.shape)


def _blendshapes(bodies: np.ndarray, template: np.ndarray, weights: np.ndarray, c_b: np.ndarray,
                 bone_basis: np.ndarray, heads: np.ndarray, frames: np.ndarray, num_shape_coeffs: int,
                 ridge: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Step 4: un-skin every body at zero pose with its bone scales, then the ridge regression of the
    offsets on c_b (the correctives, Eq. 7) and the PCA of what remains (the shape basis, Eq. 8).

    Returns:
        (correctives (Kb, 3V), shape basis (Ks, 3V), c_s (N, Ks), shape explained variance, the
        template with the residual mean added), not yet symmetrised.
    """
    n_bodies, num_bone_coeffs = c_b.shape
    b = 1.0 + c_b @ bone_basis  # (N, J)
    lin, off = (t.numpy() for t in _scaled_chain(b, heads, frames))
    f64 = torch.float64
    transforms = torch.as_tensor(np.concatenate([lin, off[..., None]], axis=-1), dtype=f64)
    unposed = unskin(torch.as_tensor(bodies, dtype=f64), torch.as_tensor(weights, dtype=f64), transforms).numpy()
    delta = (unposed - template).reshape(n_bodies, -1)
    gram = c_b.T @ c_b + ridge * n_bodies * np.eye(num_bone_coeffs)
    correctives = np.linalg.solve(gram, c_b.T @ delta)  # (Kb, 3V)
    resid = delta - c_b @ correctives
    _, ssv, svt = np.linalg.svd(resid - resid.mean(0), full_matrices=False)
    svar = ssv**2 / (n_bodies - 1)
    shape_basis = svt[:num_shape_coeffs] * np.sqrt(svar[:num_shape_coeffs, None])
    c_s = (resid - resid.mean(0)) @ svt[:num_shape_coeffs].T / np.sqrt(svar[:num_shape_coeffs])
    return correctives, shape_basis, c_s, svar / svar.sum(), template + resid.mean(0).reshape(-1, 3)


def build(
    n_bodies: int = 600,
    seed: int = 0,
    half_faces: int = 7000,
    num_bone_coeffs: int = 10,
    num_shape_coeffs: int = 16,
    ridge: float = 1e-3,
) -> tuple[io.ModelData, dict]:
    """Build the BLSM model data from an Anny population. See the module docstring."""
    import xatlas

    t0 = time.time()
    dofs = load_dof_table(DEFAULT_DOF_TABLE)
    pop = _anny_population(n_bodies, seed)
    mean_verts = pop.verts.mean(0)

    # 1. Template topology.
    dec_v, dec_f, mirror = symmetric_half_decimation(mean_verts, pop.faces, half_faces)
    tri, bary = barycentric_embedding(mean_verts, pop.faces, dec_v)
    bodies = barycentric_interpolate(pop.verts, pop.faces, tri, bary)  # (N, V, 3)
    bodies = 0.5 * (bodies + bodies[:, mirror] * _FLIP)
    template = bodies.mean(0)
    _log(f"template: {len(dec_v)} vertices, {len(dec_f)} faces (from {len(mean_verts)})")

    # 2. Weights: Anny's sparse weights summed per BLSM bone, then transferred.
    weights = _transfer_weights(pop, tri, bary, mirror)
    vertex_bones = weights.argmax(1)
    jm = pop.joints.mean(0)
    tips = _leaf_tips(template, vertex_bones, jm, mirror)

    # 3. Bone-length PCA (Sec. 4.2).
    lengths = _bone_lengths(pop.joints, bodies, tips)
    mean_len, explained, bone_basis, c_b = _bone_pca(lengths, num_bone_coeffs)
    _log(f"bone PCA: first 3 components explain {100 * explained[:3].sum():.2f} % of bone-length variance")

    # Skeleton of the template: the mean joints; frames from heads and tails.
    heads_t = jm
    tails_t, frames = _bind_skeleton(heads_t, template, tips)

    # 4. Un-skin every body at zero pose with its bone scales, then regress and PCA; the bases are
    # symmetrised exactly (the data are symmetric up to round-off).
    correctives, shape_basis, c_s, shape_explained, template = _blendshapes(
        bodies, template, weights, c_b, bone_basis, heads_t, frames, num_shape_coeffs, ridge
    )
    correctives = _symmetric_basis(correctives, mirror)
    shape_basis = _symmetric_basis(shape_basis, mirror)
    bone_mirror = [skeleton.BONE_NAMES.index(skeleton.mirror_name(n)) for n in skeleton.BONE_NAMES]
    bone_basis = 0.5 * (bone_basis + bone_basis[:, bone_mirror])
    template = 0.5 * (template + template[mirror] * _FLIP)

    # Reconstruction error of the population with the fitted coefficients (zero pose).
    recon_rest = template + (c_b @ correctives + c_s @ shape_basis).reshape(n_bodies, -1, 3)
    v2v = _population_error(bodies, recon_rest, weights, 1.0 + c_b @ bone_basis, heads_t, frames)
    _log(f"population reconstruction (zero pose, {num_bone_coeffs}+{num_shape_coeffs} coeffs): "
         f"{v2v:.2f} mm mean vertex error")

    # UVs (the decimation drops Anny's; xatlas makes an atlas on the template).
    vmap, faces_uv, uvs = xatlas.parametrize(template.astype(np.float32), dec_f.astype(np.uint32))
    if not np.array_equal(vmap[faces_uv], dec_f):
        raise RuntimeError("xatlas changed the face order or corners")

    kp_names, kp_joint, kp_vert, kp_w = _keypoints(template, dec_f, tips, pop.coco.mean(0))
    rest = _rest_flexion(heads_t, tails_t, frames)
    _log(f"rest flexion (about +x, degrees): {json.dumps({k: round(v, 1) for k, v in rest.items()})}")

    arrays = {
        "template": template.astype(np.float32),
        "faces": dec_f.astype(np.int32),
        "uvs": uvs.astype(np.float32),
        "faces_uv": faces_uv.astype(np.int32),
        "weights": weights.astype(np.float32),
        "heads": heads_t.astype(np.float64),
        "frames": frames.astype(np.float64),
        "bone_mean": np.ones(len(skeleton.BONE_PARENTS), dtype=np.float32),
        "bone_basis": bone_basis.astype(np.float32),
        "bone_correctives": correctives.reshape(num_bone_coeffs, -1, 3).astype(np.float32),
        "shape_basis": shape_basis.reshape(num_shape_coeffs, -1, 3).astype(np.float32),
        "population_bone": c_b.astype(np.float32),
        "population_shape": c_s.astype(np.float32),
        "vertex_parts": np.array(skeleton.BONE_PARTS)[vertex_bones].astype(np.int32),
        "vertex_bones": vertex_bones.astype(np.int32),
        "vertex_mirror": mirror.astype(np.int32),
        "keypoint_joint": kp_joint.astype(np.int32),
        "keypoint_vertices": kp_vert.astype(np.int32),
        "keypoint_weights": kp_w.astype(np.float32),
    }
    report = {
        "n_bodies": n_bodies,
        "seed": seed,
        "bone_pca_explained_first3": float(explained[:3].sum()),
        "bone_pca_explained": [float(x) for x in explained[:num_bone_coeffs]],
        "shape_pca_explained": [float(x) for x in shape_explained[:num_shape_coeffs]],
        "population_vertex_error_mm": float(v2v),
        "mean_bone_lengths_m": {n: float(x) for n, x in zip(skeleton.BONE_NAMES, mean_len, strict=True)},
        "rest_flexion_deg": rest,
        "source_vertices": int(len(mean_verts)),
        "seconds": round(time.time() - t0, 1),
    }
    meta = _meta(pop.version, f"blsm build-anny --bodies {n_bodies} --seed {seed}", kp_names, report)
    return io.ModelData(arrays=arrays, meta=meta, dof_table_yaml=dofs.source), report


def _bone_pca(lengths: np.ndarray, num_coeffs: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Step 3: PCA of bone lengths (N, J) relative to their mean, so ``b_mean = 1``.

    Returns:
        (mean lengths (J,) metres, explained variance fractions, basis (Kb, J) per standard
        deviation, coefficients (N, Kb) of the bodies in standard deviations).
    """
    mean_len = lengths.mean(0)
    rel = lengths / mean_len - 1.0  # b - b_mean with b_mean = 1
    _, sv, vt = np.linalg.svd(rel, full_matrices=False)
    var = sv**2 / (len(lengths) - 1)
    bone_basis = vt[:num_coeffs] * np.sqrt(var[:num_coeffs, None])  # (Kb, J)
    c_b = rel @ vt[:num_coeffs].T / np.sqrt(var[:num_coeffs])  # (N, Kb)
    return mean_len, var / var.sum(), bone_basis, c_b


def _population_error(bodies: np.ndarray, rest: np.ndarray, weights: np.ndarray, b: np.ndarray,
                      heads: np.ndarray, frames: np.ndarray) -> float:
    """Mean vertex error (mm) of the bodies (N, V, 3) rebuilt at zero pose from their T-pose
    meshes ``rest`` (N, V, 3) with bone scales ``b`` (N, J)."""
    lin, off = _scaled_chain(b, heads, frames)
    recon = linear_blend_skinning(torch.as_tensor(rest), torch.as_tensor(weights), lin, off).numpy()
    return np.linalg.norm(recon - bodies, axis=-1).mean() * 1000.0


def _meta(anny_version: str, command: str, keypoint_names: list[str], report: dict) -> dict[str, Any]:
    """The model file's metadata: names, parents, keypoint sets and the build provenance."""
    return {
        "name": "blsm-anny",
        "version": 1,
        "built": datetime.date.today().isoformat(),
        "source": f"anny {anny_version} (Apache-2.0 code, CC0 MakeHuman assets)",
        "build_command": command,
        "bone_names": list(skeleton.BONE_NAMES),
        "parents": list(skeleton.BONE_PARENTS),
        "part_names": list(skeleton.PART_NAMES),
        "keypoint_names": keypoint_names,
        "keypoint_sets": {"coco17": list(COCO17), "blsm_joints": list(skeleton.BONE_NAMES)},
        "build_report": report,
    }


def anny_mean_body(am: Any, n_bodies: int = 600, seed: int = 0) -> np.ndarray:
    """(Va, 3) mean rest body (BLSM axes) of ``n_bodies`` Anny phenotypes drawn uniformly with
    ``seed``: the surface the packaged template was cut from, on which template vertices are
    embedded by closest point (:func:`barycentric_embedding`)."""
    gen = torch.Generator().manual_seed(seed)
    pheno = torch.rand(n_bodies, len(am.phenotype_labels), generator=gen, dtype=torch.float64)
    with torch.no_grad():
        coeffs = am.get_phenotype_blendshape_coefficients(
            **{k: pheno[:, i] for i, k in enumerate(am.phenotype_labels)}
        )
        return am.get_rest_vertices(coeffs).mean(0).numpy() @ ANNY_TO_WORLD.T


def rig_of(data: io.ModelData) -> io.ModelData:
    """The rig of a model: what the learning pipeline starts from (thesis Sec. 5.4, a rigged template).

    Template, UVs, skeleton (heads, frames, DoF table), blend weights, bone basis, parts and
    keypoints are kept; the learnt blendshapes are removed (bone correctives zero, one zero shape
    component), so nothing learnt from Anny's known correspondence reaches a registration.
    """
    a = dict(data.arrays)
    a["bone_correctives"] = np.zeros_like(a["bone_correctives"])
    a["shape_basis"] = np.zeros((1, *a["template"].shape), np.float32)
    a["population_shape"] = np.zeros((len(a["population_shape"]), 1), np.float32)
    meta = {**data.meta, "name": "blsm-rig",
            "build_report": {"rig_of": f"{data.meta.get('name', '?')} ({data.meta.get('build_command', '?')})"}}
    return io.ModelData(arrays=a, meta=meta, dof_table_yaml=data.dof_table_yaml)
