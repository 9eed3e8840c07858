"""A synthetic scan population from Anny: the stand-in for CAESAR (rest scans) and D-FAUST (poses).

The thesis learns BLSM from registered scans (Sec. 5.4: CAESAR for shape, D-FAUST-like sequences
for pose). Here Anny (PyPI ``anny``) plays the scanned people:

* **Subjects.** Phenotypes (age, sex, height, weight, muscle, proportions) from Anny's WHO-calibrated
  population model (``anny.shape_distribution.SimpleShapeDistribution``), a random ethnic mix, and
  random Anny *local changes* (``local_change_labels``: local blendshapes such as "l-upperarm-fat")
  of modest amplitude for identity detail. Topology ``anny-noeyes-notongue`` at full resolution
  (13,348 vertices), world frame by ``blsm.build_anny.ANNY_TO_WORLD``, translated so that Anny's
  root joint sits on the BLSM root joint ``model.heads[0]`` (as ``blsm build-anny`` did).
* **Posing.** A BLSM pose (angles, global orient, transl) drives Anny: every Anny bone folded into
  BLSM bone j (``anny_bone_groups``) gets BLSM bone j's world rotation (BLSM forward kinematics,
  Eqs. 5.3-5.5 with unit bone scales, so no scale); forward kinematics over Anny's own bone tree and
  rest joints gives each Anny bone's rigid transform, and Anny's own skinning weights pose the
  vertices (LBS). Zero angles give Anny's rest pose (BLSM's rest A-pose, like CAESAR's standing pose).
* **Ground truth.** The BLSM template vertices are embedded once on Anny's topology by closest point
  on Anny's mean body (mean of 600 bodies, seed 0, as the model was built), as (face, barycentric).
  ``gt_points`` of a scan is that embedding evaluated on the *clean* posed Anny body (before any
  artefact): "the point of this person's skin that the template vertex stands for", exact by
  construction; it is not the registration a perfect algorithm would find on the noisy scan.
  ``gt_joints`` are the posed Anny bone heads the BLSM joints were built from (the first Anny bone
  of each BLSM bone's group, as ``blsm build-anny``), exact by the same construction.
* **Scanner artefacts** (:class:`Artefacts`): noise along the normals, holes under the arms and
  the soles, missing fingertips, a few random holes; faces removed, unreferenced vertices dropped, so
  the scan topology differs from Anny's. Landmarks are the gt landmark points plus noise (CAESAR's
  landmarking error is a few millimetres), some missing (NaN). Optionally (off by default) missing
  feet, a stool beside the body and markers on the floor (:mod:`blsm.learn.scans.scan_paint`), appended
  to the scan mesh as separate components; ``meta["props"]`` names their vertex ranges.
* **Colours**: per-vertex ``colors`` (skin, clothing-like regions, hair; :func:`scan_paint.paint_body`)
  from a random stream of their own, so the other arrays are those of an uncoloured population.

``make_population`` writes the population folder (``index.json`` + ``scans/*.npz``).
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm.build_anny import (
    ANNY_TO_WORLD,
    anny_bone_groups,
    anny_mean_body,
    barycentric_embedding,
    barycentric_interpolate,
)
from blsm.io import atomic_write
from blsm.learn.posing import pose as blsm_pose
from blsm.learn.scans.format import Scan, landmark_names, landmark_points, save_scan
from blsm.mesh import vertex_normals
from blsm.model import DEFAULT_RIG

POPULATION_FORMAT = "blsm-population"
POPULATION_VERSION = 1


def _log(msg: str) -> None:
    print(f"[scans] {msg}", file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------------------------
# Anny


@lru_cache(maxsize=1)
def anny_model() -> Any:
    """Anny (``anny-noeyes-notongue``, with the default local changes), float64, CPU."""
    import anny

    return anny.Anny(topology="anny-noeyes-notongue", local_changes="default")


@dataclass
class AnnyRig:
    """What posing Anny bodies with BLSM poses needs (precomputed once per model).

    Attributes:
        faces: (Fa, 3) int64 Anny triangles.
        weights: (Va, Ka) float64 dense Anny skinning weights.
        parents: Ka Anny bone parents (-1 for the root), topologically ordered.
        blsm_bone: (Ka,) BLSM bone of each Anny bone.
        tri: (Vb,) Anny face of each BLSM template vertex; bary: (Vb, 3) its barycentric weights.
        finger_tips: Anny vertex index sets of the ten distal finger segments.
        feet: (Va,) bool, Anny vertices skinned mostly to the feet.
    """

    faces: np.ndarray
    weights: np.ndarray
    parents: list[int]
    blsm_bone: np.ndarray
    tri: np.ndarray
    bary: np.ndarray
    finger_tips: list[np.ndarray]
    feet: np.ndarray


_RIGS: dict[int, AnnyRig] = {}


def anny_rig(model) -> AnnyRig:
    """The :class:`AnnyRig` of ``model`` (cached per model object).

    The embedding is computed on the mean of 600 Anny bodies (phenotypes uniform, seed 0, no local
    changes), the population the packaged rig's template was built from (``blsm build-anny --rig``).
    """
    key = id(model)
    if key in _RIGS:
        return _RIGS[key]
    am = anny_model()
    labels = list(am.bone_labels)
    groups = anny_bone_groups(labels)
    blsm_bone = np.zeros(len(labels), dtype=np.int64)
    for j, g in enumerate(groups):
        blsm_bone[g] = j
    parents = [int(p) for p in am.bone_parents]
    if any(p >= i for i, p in enumerate(parents)):
        raise RuntimeError("Anny's bones are not in topological order")
    mean = anny_mean_body(am)
    faces = am.faces.numpy().astype(np.int64)
    tri, bary = barycentric_embedding(mean, faces, model.template.detach().cpu().numpy().astype(np.float64))
    idx = am.vertex_bone_indices.numpy()
    w = am.vertex_bone_weights.numpy().astype(np.float64)
    dense = np.zeros((len(mean), len(labels)))
    np.add.at(dense, (np.arange(len(mean))[:, None], idx), w)
    dominant = dense.argmax(1)
    tips = []
    for side in ("L", "R"):
        for f in range(1, 6):
            bone = labels.index(f"finger{f}-3.{side}")
            tips.append(np.flatnonzero(dominant == bone))
    foot_bones = [i for i, lab in enumerate(labels) if lab.startswith(("foot.", "toe"))]
    feet = np.isin(dominant, foot_bones)
    rig = AnnyRig(faces, dense, parents, blsm_bone, tri.astype(np.int64), bary, tips, feet)
    _RIGS[key] = rig
    return rig


@dataclass
class Bodies:
    """A batch of rest Anny bodies in the BLSM world frame.

    Attributes:
        vertices: (B, Va, 3) float64 rest vertices, metres.
        heads: (B, Ka, 3) float64 rest Anny bone heads (joints), metres.
    """

    vertices: np.ndarray
    heads: np.ndarray


def rest_bodies(model, phenotypes: list[dict[str, float]], local_changes: list[dict[str, float]]) -> Bodies:
    """Anny rest bodies for a batch of phenotypes, root joint moved onto ``model.heads[0]``.

    Args:
        phenotypes: per body, Anny phenotype values in [0, 1] (missing keys: Anny's default 0.5).
        local_changes: per body, Anny local-change values in [-1, 1] (missing: 0).
    """
    from anny.skinning.skinning import apply_linear_blendshape

    am = anny_model()
    n = len(phenotypes)
    kw = {}
    for lab in am.phenotype_labels:
        kw[lab] = torch.tensor([p.get(lab, 0.5) for p in phenotypes], dtype=torch.float64)
    lc = {
        lab: torch.tensor([c.get(lab, 0.0) for c in local_changes], dtype=torch.float64)
        for lab in am.local_change_labels
    }
    with torch.no_grad():
        coeffs = am.get_phenotype_blendshape_coefficients(**kw, local_changes=lc)
        verts = am.get_rest_vertices(coeffs).numpy() @ ANNY_TO_WORLD.T  # (B, Va, 3)
        heads = (
            apply_linear_blendshape(am.template_bone_heads, am.bone_heads_blendshapes, coeffs).numpy()
            @ ANNY_TO_WORLD.T
        )
    root = model.heads[0].detach().cpu().numpy().astype(np.float64)
    shift = heads[:, :1] - root  # (B, 1, 3)
    if verts.shape[0] != n:
        raise RuntimeError("Anny returned a different batch size")
    return Bodies(verts - shift, heads - shift)


def pose_anny(
    model,
    rig: AnnyRig,
    bodies: Bodies,
    angles: torch.Tensor,
    global_orient: torch.Tensor | None = None,
    transl: torch.Tensor | None = None,
    return_heads: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Pose Anny bodies with BLSM poses (see the module docstring).

    Args:
        model: the BLSM model (its skeleton and DoF table give the bone rotations).
        rig: :func:`anny_rig` of ``model``.
        bodies: (B, Va, 3) rest bodies and their (B, Ka, 3) rest Anny joints.
        angles: (B, 47) BLSM atom angles, radians.
        global_orient: (B, 3) axis-angle about the root joint; transl: (B, 3) metres.
        return_heads: also return the (B, Ka, 3) posed Anny bone heads (:func:`posed_heads`).

    Returns:
        (B, Va, 3) float64 posed vertices (and the heads).
    """
    b = bodies.vertices.shape[0]
    if angles.shape != (b, model.num_dofs):
        raise ValueError(f"angles must be ({b}, {model.num_dofs}), got {tuple(angles.shape)}")
    with torch.no_grad():
        posed = blsm_pose(
            model,
            model.template,
            angles=angles.to(model.template.dtype),
            global_orient=None if global_orient is None else global_orient.to(model.template.dtype),
        )
    lin = posed.transforms[..., :3].double().numpy()  # (B, J, 3, 3): rotations (unit bone scales)
    u, _, vt = np.linalg.svd(lin)
    rot_j = u @ vt  # remove any round-off scale
    rot = rot_j[:, rig.blsm_bone]  # (B, Ka, 3, 3)
    heads = bodies.heads
    tr = posed_heads(rig, heads, rot, transl)  # (B, Ka, 3)
    # x -> R_k (x - h_k) + tr_k  ==  R_k x + (tr_k - R_k h_k)
    off = tr - np.einsum("bkij,bkj->bki", rot, heads)
    mats = np.concatenate([rot, off[..., None]], axis=-1).reshape(b, -1, 12)  # (B, Ka, 12)
    blended = np.einsum("vk,bkc->bvc", rig.weights, mats).reshape(b, -1, 3, 4)  # (B, Va, 3, 4)
    if return_heads:
        return np.einsum("bvij,bvj->bvi", blended[..., :3], bodies.vertices) + blended[..., 3], tr
    return np.einsum("bvij,bvj->bvi", blended[..., :3], bodies.vertices) + blended[..., 3]


def posed_heads(rig: AnnyRig, heads: np.ndarray, rot: np.ndarray, transl: torch.Tensor | None) -> np.ndarray:
    """(B, Ka, 3) posed Anny bone heads: rest heads (B, Ka, 3) moved by the bones' world rotations
    (B, Ka, 3, 3) down Anny's tree (each head moves with its parent), plus ``transl`` (B, 3)."""
    tr = np.zeros_like(heads)
    for k, p in enumerate(rig.parents):
        if p < 0:
            tr[:, k] = heads[:, k]
        else:
            tr[:, k] = np.einsum("bij,bj->bi", rot[:, p], heads[:, k] - heads[:, p]) + tr[:, p]
    if transl is not None:
        tr = tr + transl.double().numpy()[:, None]
    return tr


# ----------------------------------------------------------------------------------------------
# Scanner artefacts


@dataclass
class Artefacts:
    """Scanner artefacts applied to a clean posed body (lengths in metres).

    Attributes:
        noise: standard deviation of Gaussian noise along the vertex normals (1 mm).
        armpit_radius: radius of the hole under each arm, around the skin point nearest to a point
            8 cm below the shoulder joint and 2 cm medial of it (both scaled by body height / 1.7 m);
            0 disables.
        sole_height: faces of the feet whose vertices lie within this height of the sole and face
            down (normal y < -0.5) are removed (the scanner cannot see the soles); 0 disables.
        fingertip_rate: probability that each distal finger segment is missing.
        random_holes: number of extra small holes at random vertices.
        random_hole_radius: their radius.
        landmark_noise: RMS 3D landmark location error (5 mm; Gaussian, landmark_noise / sqrt(3)
            per axis, so the median 3D error is about 4.4 mm).
        landmark_missing: probability that a landmark is not located (NaN row).
        missing_feet: remove both feet (Anny vertices skinned mostly to the feet and toes).
        stool: add a stool (a 0.45 m closed cylinder) on the floor beside the body.
        floor_markers: number of small flat discs on the floor around the body.
    """

    noise: float = 0.001
    armpit_radius: float = 0.045
    sole_height: float = 0.012
    fingertip_rate: float = 0.5
    random_holes: int = 3
    random_hole_radius: float = 0.015
    landmark_noise: float = 0.005
    landmark_missing: float = 0.03
    missing_feet: bool = False
    stool: bool = False
    floor_markers: int = 0

    def __post_init__(self) -> None:
        for k, v in asdict(self).items():
            if v < 0:
                raise ValueError(f"Artefacts.{k} must be >= 0, got {v}")
        if self.fingertip_rate > 1 or self.landmark_missing > 1:
            raise ValueError("Artefacts rates must be in [0, 1]")


NO_ARTEFACTS = Artefacts(0.0, 0.0, 0.0, 0.0, 0, 0.0, 0.0, 0.0)


def hole_vertices(
    rest: np.ndarray,
    heads: np.ndarray,
    rig: AnnyRig,
    art: Artefacts,
    rng: np.random.Generator,
    labels: list[str],
) -> tuple[np.ndarray, dict[str, int]]:
    """(Va,) bool: Anny vertices a scanner misses, chosen on the rest body; and counts per cause."""
    miss = np.zeros(len(rest), dtype=bool)
    counts = {}
    height = rest[:, 1].max() - rest[:, 1].min()
    s = height / 1.7
    if art.armpit_radius > 0:
        for side, sign in (("L", 1.0), ("R", -1.0)):
            sh = heads[labels.index(f"upperarm01.{side}")]
            inner = sh + s * np.array([-0.02 * sign, -0.08, 0.0])  # inside the body, under the joint
            centre = rest[np.argmin(np.linalg.norm(rest - inner, axis=1))]  # nearest skin: the armpit
            m = np.linalg.norm(rest - centre, axis=1) < art.armpit_radius * s
            miss |= m
            counts[f"armpit_{side.lower()}"] = int(m.sum())
    if art.sole_height > 0:
        normals = vertex_normals(rest, rig.faces)
        low = rest[:, 1] < rest[rig.feet, 1].min() + art.sole_height
        m = rig.feet & low & (normals[:, 1] < -0.5)
        miss |= m
        counts["soles"] = int(m.sum())
    tips = 0
    for tip in rig.finger_tips:
        if rng.random() < art.fingertip_rate:
            miss[tip] = True
            tips += 1
    counts["fingertips"] = tips
    if art.missing_feet:
        miss |= rig.feet
        counts["feet"] = int(rig.feet.sum())
    for _ in range(art.random_holes):
        c = rest[rng.integers(len(rest))]
        miss |= np.linalg.norm(rest - c, axis=1) < art.random_hole_radius
    counts["random_holes"] = art.random_holes
    return miss, counts


def make_scan_mesh(
    posed: np.ndarray, faces: np.ndarray, miss: np.ndarray, noise: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Apply noise along the normals, remove faces touching missed vertices, drop unused vertices."""
    v = posed.copy()
    if noise > 0:
        v += vertex_normals(posed, faces) * rng.normal(0.0, noise, size=(len(v), 1))
    keep = ~miss[faces].any(1)
    f = faces[keep]
    used = kept_vertices(faces, miss)
    remap = np.full(len(v), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return v[used].astype(np.float32), remap[f].astype(np.int32)


def kept_vertices(faces: np.ndarray, miss: np.ndarray) -> np.ndarray:
    """(N,) the Anny vertices a scan keeps, in the scan's vertex order (:func:`make_scan_mesh`)."""
    return np.unique(faces[~miss[faces].any(1)])


# ----------------------------------------------------------------------------------------------
# Subjects


@lru_cache(maxsize=1)
def _shape_distribution() -> Any:
    from anny.shape_distribution import SimpleShapeDistribution

    return SimpleShapeDistribution(anny_model())


def sample_subject(
    index: int, seed: int, local_amplitude: float = 0.3, local_fraction: float = 0.2
) -> dict[str, Any]:
    """Phenotype and local changes of subject ``index``: a function of (seed, index) only.

    Anny's population model (WHO-calibrated: age over 0-90 years, sex, then height, weight,
    muscle and proportions from Beta distributions given age and sex), a Dirichlet ethnic mix,
    and a random ``local_fraction`` of Anny's local changes drawn uniformly in
    ``[-local_amplitude, local_amplitude]``.
    """
    rng = np.random.default_rng([seed, index, 0])
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(rng.integers(2**62)))
        years, ph = _shape_distribution().sample(1)
    pheno = {k: float(v.reshape(-1)[0]) for k, v in ph.items()}
    mix = rng.dirichlet([1.0, 1.0, 1.0])
    pheno.update(african=float(mix[0]), asian=float(mix[1]), caucasian=float(mix[2]))
    labels = anny_model().local_change_labels
    chosen = rng.random(len(labels)) < local_fraction
    values = rng.uniform(-local_amplitude, local_amplitude, size=len(labels))
    local = {lab: float(v) for lab, v, c in zip(labels, values, chosen, strict=True) if c}
    return {"phenotype": pheno, "age_years": float(years.reshape(-1)[0]), "local_changes": local}


@lru_cache(maxsize=1)
def _default_prior():
    from blsm.mocap.prior import load_prior

    return load_prior(Path(__file__).resolve().parents[2] / "data" / "pose_prior_cmu.npz")


def sample_poses(
    model, n: int, rng: np.random.Generator, motions: list[Path] | None = None
) -> tuple[torch.Tensor, torch.Tensor, list[str]]:
    """n poses: angles (n, 47) radians, global orient (n, 3) = a random rotation about Y, sources.

    From the packaged CMU pose prior, or from random frames of a motion library's clips.
    """
    from blsm.joint_limits import angles_from_unconstrained

    yaw = rng.uniform(-np.pi, np.pi, size=n)
    orient = torch.zeros(n, 3, dtype=torch.float64)
    orient[:, 1] = torch.as_tensor(yaw)
    if motions:
        from blsm.mocap.library import load_clip

        xs, src = [], []
        for _ in range(n):
            path = motions[int(rng.integers(len(motions)))]
            clip = load_clip(path)
            t = int(rng.integers(clip.num_frames))
            xs.append(clip.pose[t])
            src.append(f"{path.stem}:{t}")
        x = torch.as_tensor(np.stack(xs), dtype=model.dof_limits.dtype)
        angles = angles_from_unconstrained(x, model.dof_limits)
    else:
        gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
        prior = _default_prior()
        angles = prior.angles(prior.sample(n, gen))
        src = ["prior:pose_prior_cmu"] * n
    return angles.double(), orient, src


def _make_scans(
    model,
    rig: AnnyRig,
    subjects: list[dict[str, Any]],
    jobs: list[tuple[int, int, torch.Tensor, torch.Tensor, str]],
    art: Artefacts,
    seed: int,
    colors: bool = True,
) -> list[Scan]:
    """Scans for jobs (subject position, pose number, angles (47,), orient (3,), source)."""
    from blsm.build_anny import anny_bone_groups
    from blsm.learn.scans.scan_paint import add_props, paint_body

    am = anny_model()
    labels = list(am.bone_labels)
    bodies = rest_bodies(
        model, [subjects[j[0]]["phenotype"] for j in jobs], [subjects[j[0]]["local_changes"] for j in jobs]
    )
    angles = torch.stack([j[2] for j in jobs])
    orient = torch.stack([j[3] for j in jobs])
    posed, heads = pose_anny(model, rig, bodies, angles, orient, return_heads=True)
    gt_joints = heads[:, [g[0] for g in anny_bone_groups(labels)]]  # (B, J, 3): as blsm build-anny
    gt = barycentric_interpolate(posed, rig.faces, rig.tri, rig.bary)  # (B, Vb, 3)
    lm_names = landmark_names()
    lm_gt = landmark_points(torch.as_tensor(gt)).numpy()  # (B, L, 3)
    scans = []
    for b, (si, k, ang, ori, src) in enumerate(jobs):
        sub = subjects[si]
        rng = np.random.default_rng([seed, sub["index"], 3, k])
        miss, counts = hole_vertices(bodies.vertices[b], bodies.heads[b], rig, art, rng, labels)
        v, f = make_scan_mesh(posed[b], rig.faces, miss, art.noise, rng)
        lm = lm_gt[b] + rng.normal(0.0, art.landmark_noise / np.sqrt(3.0), size=lm_gt[b].shape)
        lm[rng.random(len(lm)) < art.landmark_missing] = np.nan
        # Colours and props draw from streams of their own: the arrays above stay as without them.
        paint = paint_body(bodies.vertices[b], rig.weights, labels, sub["phenotype"],
                           np.random.default_rng([seed, sub["index"], 4]))
        col = paint[kept_vertices(rig.faces, miss)]
        props: dict[str, list[int]] = {}
        if art.stool or art.floor_markers:
            v, f, col, props = add_props(v, f, col, posed[b], art.stool, art.floor_markers,
                                         np.random.default_rng([seed, sub["index"], 5, k]))
        meta = {
            "id": f"{sub['id']}_{k:02d}",
            "subject": sub["id"],
            "pose": k,
            "pose_source": src,
            "source": f"anny {getattr(__import__('anny'), '__version__', '?')}",
            "phenotype": sub["phenotype"],
            "age_years": sub["age_years"],
            "local_changes": sub["local_changes"],
            "height_m": float(bodies.vertices[b][:, 1].max() - bodies.vertices[b][:, 1].min()),
            "artefacts": {**asdict(art), "removed_vertices": int(miss.sum()), **counts},
            "gt": "gt_points = BLSM template vertices embedded on Anny's topology, on the clean posed body",
            "props": props,
        }
        scans.append(
            Scan(
                v,
                f,
                lm_names,
                lm.astype(np.float32),
                meta,
                gt.astype(np.float32)[b],
                ang.float().numpy(),
                ori.float().numpy(),
                np.zeros(3, np.float32),
                gt_joints=gt_joints[b].astype(np.float32),
                colors=col if colors else None,
            )
        )
    return scans


def make_population(
    out: str | Path,
    n_subjects: int,
    posed_subjects: int = 0,
    poses_per_subject: int = 0,
    seed: int = 0,
    test_fraction: float = 0.1,
    artefacts: Artefacts | None = None,
    motions: str | Path | None = None,
    overwrite: bool = False,
    batch: int = 8,
    model=None,
    colors: bool = True,
) -> dict[str, Any]:
    """Write a scan population folder (``index.json`` + ``scans/*.npz``).

    Args:
        out: the folder.
        n_subjects: number of subjects; each has a rest scan (angles 0) first.
        posed_subjects: the first ``posed_subjects`` subjects also get ``poses_per_subject`` posed
            scans (pose prior or motion library, random rotation about Y).
        seed: every random draw derives from (seed, subject index), so a subset is reproducible.
        test_fraction: probability that a subject is held out (``split = "test"``, per subject).
        artefacts: scanner artefacts (default :class:`Artefacts`).
        motions: a motion library folder (``blsm/mocap/library.py``) instead of the pose prior.
        overwrite: replace an existing population.
        batch: scans posed together through Anny.
        model: the BLSM model (default: the packaged one).
        colors: paint per-vertex colours (:func:`scan_paint.paint_body`).

    Returns:
        The index (also written as ``index.json``).
    """
    import blsm

    out = Path(out)
    if n_subjects < 1 or posed_subjects < 0 or poses_per_subject < 0 or posed_subjects > n_subjects:
        raise ValueError(
            f"need n_subjects >= 1 and 0 <= posed_subjects <= n_subjects, got {n_subjects}, {posed_subjects}"
        )
    if not 0.0 <= test_fraction <= 1.0:
        raise ValueError(f"test_fraction must be in [0, 1], got {test_fraction}")
    if (out / "index.json").exists() and not overwrite:
        raise ValueError(f"{out}: a population already exists (use overwrite=True / --overwrite)")
    art = Artefacts() if artefacts is None else artefacts
    model = blsm.load(DEFAULT_RIG) if model is None else model  # the template fixes the ground truth
    t0 = time.time()
    rig = anny_rig(model)
    clips = None
    if motions is not None:
        from blsm.mocap.library import list_clips

        clips = list_clips(motions)
    _log(f"Anny rig and template embedding ready in {time.time() - t0:.1f} s")
    subjects, jobs = [], []
    zero = torch.zeros(model.num_dofs, dtype=torch.float64)
    for i in range(n_subjects):
        info = sample_subject(i, seed)
        split = "test" if np.random.default_rng([seed, i, 1]).random() < test_fraction else "train"
        sub = {"id": f"s{i:05d}", "index": i, "split": split, **info}
        subjects.append(sub)
        jobs.append((i, 0, zero, torch.zeros(3, dtype=torch.float64), "rest"))
        if i < posed_subjects and poses_per_subject:
            ang, ori, src = sample_poses(model, poses_per_subject, np.random.default_rng([seed, i, 2]), clips)
            for k in range(poses_per_subject):
                jobs.append((i, k + 1, ang[k], ori[k], src[k]))
    files: dict[int, list[str]] = {i: [] for i in range(n_subjects)}
    t1 = time.time()
    last_log = 0.0
    for start in range(0, len(jobs), batch):
        chunk = jobs[start : start + batch]
        for scan in _make_scans(model, rig, subjects, chunk, art, seed, colors):
            rel = f"scans/{scan.meta['id']}.npz"
            save_scan(scan, out / rel)
            files[int(scan.meta["subject"][1:])].append(rel)
        done = min(start + batch, len(jobs))
        rate = (time.time() - t1) / done
        if time.time() - last_log >= 30 or done == len(jobs):  # a line every 30 s, and the last
            last_log = time.time()
            _log(f"{done}/{len(jobs)} scans, {rate:.2f} s per scan, about {rate * (len(jobs) - done):.0f} s left")
    index = {
        "format": POPULATION_FORMAT,
        "version": POPULATION_VERSION,
        "seed": seed,
        "test_fraction": test_fraction,
        "artefacts": asdict(art),
        "pose_source": str(motions) if motions is not None else "blsm/data/pose_prior_cmu.npz",
        "subjects": [
            {
                "id": s["id"],
                "split": s["split"],
                "phenotype": {**s["phenotype"], "age_years": s["age_years"]},
                "scans": files[s["index"]],
            }
            for s in subjects
        ],
        "seconds": round(time.time() - t0, 1),
    }
    with atomic_write(out / "index.json", "w") as fh:
        json.dump(index, fh, indent=1)
    return index


def read_population(folder: str | Path) -> dict[str, Any]:
    """Read and check ``folder/index.json``; scan paths are relative to ``folder``."""
    path = Path(folder) / "index.json"
    try:
        index = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: cannot read population index ({e})") from None
    if (
        not isinstance(index, dict)
        or index.get("format") != POPULATION_FORMAT
        or index.get("version") != POPULATION_VERSION
    ):
        raise ValueError(f"{path}: not a {POPULATION_FORMAT} v{POPULATION_VERSION} index")
    for s in index.get("subjects", []):
        if s.get("split") not in ("train", "test") or not s.get("scans"):
            raise ValueError(f"{path}: subject {s.get('id')!r} needs split train|test and at least one scan")
    return index


def render_preview(
    folder: str | Path, path: str | Path, n: int = 8, tile: tuple[int, int] = (260, 360)
) -> Path:
    """Contact sheet of the first ``n`` scans of a population with their landmarks (PNG).

    Each scan is drawn from the front-left and raised (so holes under the arms and feet show);
    landmarks are dots (left blue, right red, midline green), missing ones are not drawn.
    """
    from PIL import Image, ImageDraw

    from blsm import render
    from blsm.camera import auto_camera
    from blsm.learn.scans.format import load_scan

    folder = Path(folder)
    index = read_population(folder)
    rels = [r for s in index["subjects"] for r in s["scans"]][:n]
    w, h = tile
    cols = min(4, len(rels))
    sheet = Image.new("RGB", (cols * w, -(-len(rels) // cols) * h), (255, 255, 255))
    for i, rel in enumerate(rels):
        scan = load_scan(folder / rel)
        mesh = (scan.vertices.astype(np.float64), scan.faces.astype(np.int64))
        cam = auto_camera([mesh], w, h, azimuth_deg=-35.0, elevation_deg=-20.0)
        img = render.render_meshes([mesh], cam, spp=8)
        t = Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8))
        draw = ImageDraw.Draw(t)
        ok = scan.located
        for name, (u, v) in zip(
            np.array(scan.landmark_names)[ok], cam.project(scan.landmarks[ok].astype(np.float64)), strict=True
        ):
            col = (
                (30, 60, 230)
                if name.endswith("_l")
                else (220, 30, 30)
                if name.endswith("_r")
                else (0, 160, 0)
            )
            draw.ellipse([u - 2, v - 2, u + 2, v + 2], fill=col)
        draw.text(
            (4, 4),
            f"{scan.meta['id']} {scan.meta['age_years']:.0f}y {scan.meta['height_m']:.2f}m",
            fill=(0, 0, 0),
        )
        sheet.paste(t, ((i % cols) * w, (i // cols) * h))
    return render.save_png(np.asarray(sheet), path)
