"""Subjects: a scan, its BLSM registration, and the rig the generator poses (thesis Sec. 6.4.3).

A subject is what the thesis' Fig. 6.11 starts from: a textured scan in its own pose and its BLSM
registration (bone and shape coefficients, pose, and per-vertex displacements ``D`` in the model's
rest frame, so that LBS of ``template + blendshapes + D`` reproduces the scan's surface). From
them this module makes the rig of the ``rigged`` pipeline:

1. **Weight painting:** each scan vertex takes the LBS weights of its nearest registration vertex.
2. **Subject T-pose template:** inverse LBS with the registration's skinning transforms (the blend
   of the per-bone inverses, the usual approximation), then refined: the template's vertices are
   optimised so that posing them with the registration's pose reproduces the scan. LBS is linear
   in the template vertices, so the optimum is the per-vertex solve of the blended transform; the
   report keeps the residual before and after.

Posing a subject (:func:`pose_subject`) is LBS of that template with the painted weights and the
skinning transforms of any BLSM pose with the subject's bone coefficients.

The default subjects are people sampled from Anny (:func:`anny_subject`) as stand-in scans at Anny's
full resolution with a procedural UV texture (:mod:`synth.textures`); their registration is a fit of
BLSM to them through Anny's known correspondence.

File format ("blsm-subject" v1, one ``.npz`` per subject, written atomically): arrays
``vertices`` (V, 3), ``faces`` (F, 3), ``uv`` (U, 2), ``faces_uv`` (F, 3), ``texture`` (H, W, 3) uint8
sRGB, ``weights`` (V, J), ``template`` (V, 3), ``reg_bone``, ``reg_shape``, ``reg_angles`` (47, radians),
``reg_global_orient`` (3), ``reg_transl`` (3), ``reg_displacement`` (Vb, 3), and ``meta`` (JSON).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm import io as blsm_io
from blsm.lbs import linear_blend_skinning, unskin
from blsm.model import BLSM

FORMAT = "blsm-subject"
VERSION = 1
PIPELINES = ("rigged", "raw", "blsm")

_REG_KEYS = ("bone", "shape", "angles", "global_orient", "transl", "displacement")


@dataclass
class Subject:
    """One person: scan mesh, texture, registration and rig (see the module docstring).

    Attributes:
        id: name, unique in a dataset.
        vertices: (V, 3) the scan in its own pose, metres, world frame (Y up).
        faces: (F, 3) triangles of the scan.
        uv: (U, 2) texture coordinates (v up); faces_uv (F, 3) indexes them.
        texture: (H, W, 3) uint8 sRGB albedo, row 0 at v = 1.
        weights: (V, J) painted LBS weights.
        template: (V, 3) subject T-pose template in the model's rest frame.
        registration: ``bone`` (Kb,), ``shape`` (Ks,), ``angles`` (47,) radians, ``global_orient`` (3,),
            ``transl`` (3,), ``displacement`` (Vb, 3), as float32 arrays.
        meta: JSON-able description (source, phenotype, outfit, fit residuals).
    """

    id: str
    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    faces_uv: np.ndarray
    texture: np.ndarray
    weights: np.ndarray
    template: np.ndarray
    registration: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def vertex_bones(self) -> np.ndarray:
        """(V,) the bone of largest painted weight of every scan vertex."""
        return self.weights.argmax(1)


# ------------------------------------------------------------------------------------------------
# Registration-driven rigging


def registration_output(
    model: BLSM, reg: dict[str, np.ndarray], pose: np.ndarray | None = None, **override: np.ndarray
) -> tuple[torch.Tensor, torch.Tensor, Any]:
    """The registration posed: (Vb, 3) vertices with displacements, (J, 3, 4) transforms, output.

    Args:
        reg: the registration (its ``angles`` are the scan's pose).
        pose: (47,) unconstrained atom values x (Eq. 6) to pose it with instead of its angles.
        override: ``global_orient`` / ``transl`` to use instead of the registration's.
    """
    p = {**reg, **override}
    t = {k: torch.as_tensor(np.asarray(v), dtype=torch.float32)[None] for k, v in p.items()}
    kw = {"pose": torch.as_tensor(np.asarray(pose), dtype=torch.float32)[None]} if pose is not None else {"angles": t["angles"]}
    out = model(bone=t["bone"], shape=t["shape"], global_orient=t["global_orient"], transl=t["transl"], **kw)
    tr = out.skinning_transforms
    verts = linear_blend_skinning(out.template + t["displacement"], model.weights, tr[..., :3], tr[..., 3])
    return verts[0], tr[0], out


def paint_weights(
    scan_vertices: np.ndarray,
    reg_vertices: np.ndarray,
    reg_weights: np.ndarray,
    scan_faces: np.ndarray | None = None,
    reg_faces: np.ndarray | None = None,
    k: int = 16,
    min_cos: float = 0.3,
) -> np.ndarray:
    """Thesis Sec. 6.4.3: each scan vertex takes the weights of its nearest registration vertex.

    With faces given, the nearest of the ``k`` nearest registration vertices whose normal agrees
    with the scan vertex's (cosine above ``min_cos``) is taken, so a forearm vertex resting against
    the thigh is not painted with the thigh's weights; where none agrees, the nearest one.

    Args:
        scan_vertices: (V, 3); reg_vertices: (Vb, 3) in the same pose; reg_weights: (Vb, J).
        scan_faces, reg_faces: (F, 3) triangles, for the normal test (optional).

    Returns:
        (V, J) float32 weights.
    """
    from scipy.spatial import cKDTree

    tree = cKDTree(reg_vertices)
    if scan_faces is None or reg_faces is None:
        _, nearest = tree.query(scan_vertices)
    else:
        from blsm.mesh import vertex_normals

        kk = min(k, len(reg_vertices))
        _, cand = tree.query(scan_vertices, k=kk)  # (V, k), nearest first
        ns = vertex_normals(np.asarray(scan_vertices, np.float32), np.asarray(scan_faces))
        nr = vertex_normals(np.asarray(reg_vertices, np.float32), np.asarray(reg_faces))
        ok = np.einsum("vc,vkc->vk", ns, nr[cand]) > min_cos
        first = np.where(ok.any(1), ok.argmax(1), 0)
        nearest = cand[np.arange(len(cand)), first]
    return np.ascontiguousarray(reg_weights[nearest], dtype=np.float32)


def unpose_template(
    scan_vertices: np.ndarray, weights: np.ndarray, transforms: np.ndarray
) -> tuple[np.ndarray, dict[str, float]]:
    """Subject T-pose template from a scan, its painted weights and the registration's transforms.

    Inverse LBS (blended per-bone inverses) gives the start; the refinement minimises
    ``sum_i || LBS(T)_i - s_i ||^2`` over the template vertices T. LBS is linear in T (posed
    ``A_i T_i + b_i`` with ``A_i = sum_j w_ij L_j``), so the minimum is ``T_i = A_i^-1 (s_i - b_i)``.

    Args:
        scan_vertices: (V, 3) posed scan.
        weights: (V, J) painted weights.
        transforms: (J, 3, 4) skinning transforms [L_j | t_j] of the registration (Eq. 12).

    Returns:
        (V, 3) template and a report: ``inverse_lbs_mm`` and ``refined_mm`` (mean and max posing
        residual in millimetres of the start and of the refined template).
    """
    s = np.asarray(scan_vertices, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    tr = np.asarray(transforms, dtype=np.float64)
    lin, off = tr[:, :, :3], tr[:, :, 3]
    inv_lin = np.linalg.inv(lin)  # (J, 3, 3)
    inv_off = -np.einsum("jab,jb->ja", inv_lin, off)
    start = np.einsum("vj,jab,vb->va", w, inv_lin, s) + w @ inv_off

    a = np.einsum("vj,jab->vab", w, lin)  # (V, 3, 3)
    b = w @ off

    def residual(t: np.ndarray) -> np.ndarray:
        return np.linalg.norm(np.einsum("vab,vb->va", a, t) + b - s, axis=1) * 1000.0

    refined = np.linalg.solve(a, (s - b)[..., None])[..., 0]
    r0, r1 = residual(start), residual(refined)
    report = {
        "inverse_lbs_mean_mm": float(r0.mean()),
        "inverse_lbs_max_mm": float(r0.max()),
        "refined_mean_mm": float(r1.mean()),
        "refined_max_mm": float(r1.max()),
    }
    return refined.astype(np.float32), report


def rig_subject(
    model: BLSM,
    subject_id: str,
    vertices: np.ndarray,
    faces: np.ndarray,
    uv: np.ndarray,
    faces_uv: np.ndarray,
    texture: np.ndarray,
    registration: dict[str, np.ndarray],
    meta: dict[str, Any] | None = None,
) -> Subject:
    """Paint weights from the registration and solve the subject's T-pose template."""
    reg = {k: np.asarray(registration[k], dtype=np.float32) for k in _REG_KEYS}
    check_registration(model, reg, subject_id)
    with torch.no_grad():
        reg_verts, tr, _ = registration_output(model, reg)
    weights = paint_weights(vertices, reg_verts.numpy(), model.weights.numpy(), faces, model.faces.numpy())
    template, report = unpose_template(vertices, weights, tr.numpy())
    meta = dict(meta or {})
    meta["rig"] = report
    return Subject(
        id=subject_id,
        vertices=np.asarray(vertices, dtype=np.float32),
        faces=np.asarray(faces, dtype=np.int32),
        uv=np.asarray(uv, dtype=np.float32),
        faces_uv=np.asarray(faces_uv, dtype=np.int32),
        texture=np.asarray(texture, dtype=np.uint8),
        weights=weights,
        template=template,
        registration=reg,
        meta=meta,
    )


def model_fingerprint(model: BLSM) -> str:
    """SHA-256 (hex) of a model's arrays and metadata: what a registration's parameters refer to."""
    import hashlib

    h = hashlib.sha256(json.dumps(model.meta, sort_keys=True, default=str).encode())
    for name, t in sorted(model.named_buffers()):
        h.update(name.encode())
        h.update(np.ascontiguousarray(t.detach().cpu().numpy()).tobytes())
    return h.hexdigest()


def check_registration(model: BLSM, reg: dict[str, np.ndarray], where: str) -> None:
    """Raise ValueError naming ``where`` if a registration does not fit the model."""
    sizes = {
        "bone": (model.num_bone_coeffs,),
        "shape": (model.num_shape_coeffs,),
        "angles": (model.num_dofs,),
        "global_orient": (3,),
        "transl": (3,),
        "displacement": (model.num_vertices, 3),
    }
    for k, shape in sizes.items():
        if k not in reg:
            raise ValueError(f"{where}: registration has no {k!r}")
        v = np.asarray(reg[k])
        if v.shape != shape:
            raise ValueError(f"{where}: registration {k!r} has shape {v.shape}, the model needs {shape}")
        if not np.isfinite(v).all():
            raise ValueError(f"{where}: registration {k!r} has NaN or inf")


# ------------------------------------------------------------------------------------------------
# Posing


def pose_subject(
    subject: Subject, model: BLSM, params: dict[str, np.ndarray], pipeline: str = "rigged"
) -> dict[str, np.ndarray]:
    """The subject's mesh and keypoints in one pose.

    Args:
        subject: the subject.
        model: the BLSM model.
        params: ``pose`` (47,) unconstrained values x, ``global_orient`` (3,), ``transl`` (3,) (the
            subject's own bone and shape coefficients are used). Ignored by the ``raw`` pipeline,
            which shows the scan in its own pose (the registration's angles; ``pose`` is then None).
        pipeline: ``rigged`` (the subject template posed with the painted weights), ``raw``, or
            ``blsm`` (the registration mesh with displacements posed, BLSM topology).

    Returns:
        ``vertices`` (V, 3), ``faces`` (F, 3), ``vertex_bones`` (V,) and, from the registration in
        that pose, ``keypoints`` (K, 3), ``joints`` (J, 3), ``angles`` (47,), ``bone_scales`` (J,),
        ``transforms`` (J, 3, 4) the skinning transforms (for :func:`synth.hair.pose_hair`), and the
        parameters used (``pose``, ``global_orient``, ``transl``, ``bone``, ``shape``).
    """
    if pipeline not in PIPELINES:
        raise ValueError(f"unknown pipeline {pipeline!r} (known: {', '.join(PIPELINES)})")
    reg = subject.registration
    if pipeline == "raw":
        pose, over = None, {}
    else:
        pose = np.asarray(params["pose"], dtype=np.float32)
        over = {k: np.asarray(params[k], dtype=np.float32) for k in ("global_orient", "transl")}
    p = {**reg, **over}
    with torch.no_grad():
        reg_verts, tr, out = registration_output(model, reg, pose, **over)
        keypoints = model._keypoints(reg_verts[None], out.joints)[0]
        if pipeline == "rigged":
            verts = linear_blend_skinning(
                torch.as_tensor(subject.template)[None], torch.as_tensor(subject.weights), tr[None, :, :, :3], tr[None, :, :, 3]
            )[0].numpy()
            faces, bones = subject.faces, subject.vertex_bones
        elif pipeline == "raw":
            verts, faces, bones = subject.vertices, subject.faces, subject.vertex_bones
        else:
            verts, faces, bones = reg_verts.numpy(), model.faces.numpy(), model.vertex_bones.numpy()
    return {
        "vertices": np.asarray(verts, dtype=np.float32),
        "faces": np.asarray(faces, dtype=np.int32),
        "vertex_bones": np.asarray(bones),
        "keypoints": keypoints.numpy(),
        "joints": out.joints[0].numpy(),
        "angles": out.angles[0].numpy(),
        "bone_scales": out.bone_scales[0].numpy(),
        "rest_joints": out.rest_joints[0].numpy(),
        "transforms": tr.numpy(),
        "pose": None if pose is None else pose,
        **{k: np.asarray(p[k], dtype=np.float32) for k in ("global_orient", "transl", "bone", "shape")},
    }


# ------------------------------------------------------------------------------------------------
# Files


def save_subject(subject: Subject, path: str | Path) -> Path:
    """Write a subject file atomically ("blsm-subject" v1)."""
    path = Path(path)
    arrays = {
        "vertices": subject.vertices,
        "faces": subject.faces,
        "uv": subject.uv,
        "faces_uv": subject.faces_uv,
        "texture": subject.texture,
        "weights": subject.weights,
        "template": subject.template,
        **{f"reg_{k}": subject.registration[k] for k in _REG_KEYS},
    }
    meta = {"format": FORMAT, "version": VERSION, "id": subject.id, **subject.meta}
    arrays["meta"] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)
    with blsm_io.atomic_write(path) as f:
        np.savez(f, **arrays)
    return path


def load_subject(path: str | Path) -> Subject:
    """Read and check a subject file; errors name the file."""
    path = Path(path)
    a = blsm_io.read_npz(path, "subject")
    need = ("vertices", "faces", "uv", "faces_uv", "texture", "weights", "template", "meta")
    for k in need + tuple(f"reg_{k}" for k in _REG_KEYS):
        if k not in a:
            raise ValueError(f"{path}: subject file has no array {k!r}")
    try:
        meta = json.loads(a["meta"].tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: unreadable subject metadata ({exc})") from None
    if meta.get("format") != FORMAT:
        raise ValueError(f"{path}: not a {FORMAT} file")
    v, f = a["vertices"], a["faces"]
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"{path}: vertices/faces must be (V, 3)/(F, 3), got {v.shape}/{f.shape}")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"{path}: faces index outside [0, {len(v)})")
    if a["weights"].shape[0] != len(v) or a["template"].shape != v.shape:
        raise ValueError(f"{path}: weights/template do not match {len(v)} vertices")
    if a["faces_uv"].shape != f.shape:
        raise ValueError(f"{path}: faces_uv must match faces {f.shape}")
    for k in ("vertices", "weights", "template", "uv"):
        if not np.isfinite(a[k]).all():
            raise ValueError(f"{path}: {k} has NaN or inf")
    sid = meta.pop("id")
    meta.pop("format"), meta.pop("version")
    return Subject(
        id=sid,
        vertices=a["vertices"],
        faces=a["faces"],
        uv=a["uv"],
        faces_uv=a["faces_uv"],
        texture=a["texture"],
        weights=a["weights"],
        template=a["template"],
        registration={k: a[f"reg_{k}"] for k in _REG_KEYS},
        meta=meta,
    )


# ------------------------------------------------------------------------------------------------
# Anny stand-in scans


@lru_cache(maxsize=1)
def _anny() -> Any:
    import anny

    return anny.Anny(topology="anny-noeyes-notongue")


def _anny_embedding(model: BLSM) -> tuple[np.ndarray, np.ndarray]:
    """Where each BLSM template vertex lies on Anny's surface: (face (Vb,), barycentric (Vb, 3)).

    The packaged rig's template (:data:`blsm.model.DEFAULT_RIG`, ``blsm build-anny --rig``) lies on
    the mean of 600 Anny bodies (seed 0); its vertices are embedded on that same mean surface by
    closest point. A model with the rig's topology (the packaged one, learnt from it) uses the
    rig's template, so the embedding does not depend on what the model learnt; a model of another
    topology uses its own template.
    """
    from blsm import io
    from blsm.build_anny import anny_mean_body, barycentric_embedding
    from blsm.model import DEFAULT_RIG

    key = (id(model), model.num_vertices)
    if key in _EMBEDDING:
        return _EMBEDDING[key]
    am = _anny()
    verts = anny_mean_body(am)
    template = io.read_model(DEFAULT_RIG).arrays["template"]
    if template.shape[0] != model.num_vertices:
        template = model.template.numpy()
    _EMBEDDING[key] = barycentric_embedding(verts, am.faces.numpy(), template.astype(np.float64))
    return _EMBEDDING[key]


_EMBEDDING: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}


def fit_registration(model: BLSM, target: np.ndarray, steps: int = 300) -> tuple[dict[str, np.ndarray], dict]:
    """Fit BLSM bone and shape coefficients and a translation to a rest-pose body in correspondence.

    Minimises the mean squared vertex distance (Adam), then sets the displacements ``D`` so that the
    registration reproduces ``target`` exactly: ``D_i = A_i^-1 (target_i - b_i) - T_i`` with the
    blended transform of vertex i.

    Args:
        target: (Vb, 3) body in the model's topology, rest pose, metres.

    Returns:
        The registration and a report (``fit_mean_mm``: mean vertex error before displacements).
    """
    tgt = torch.as_tensor(target, dtype=torch.float32)[None]
    bone = torch.zeros(1, model.num_bone_coeffs, requires_grad=True)
    shape = torch.zeros(1, model.num_shape_coeffs, requires_grad=True)
    transl = (tgt.mean(1) - model.template.mean(0)).clone().requires_grad_(True)
    opt = torch.optim.Adam([bone, shape, transl], lr=0.05)
    for _ in range(steps):
        opt.zero_grad()
        out = model(bone=bone, shape=shape, transl=transl)
        loss = ((out.vertices - tgt) ** 2).sum(-1).mean() * 1e4
        loss.backward()
        opt.step()
    with torch.no_grad():
        out = model(bone=bone, shape=shape, transl=transl)
        err = (out.vertices - tgt).norm(dim=-1).mean().item() * 1000.0
        f64 = torch.float64
        rest = unskin(torch.as_tensor(target, dtype=f64), model.weights.to(f64), out.skinning_transforms[0].to(f64))
        disp = rest.numpy() - out.template[0].numpy()
    reg = {
        "bone": bone.detach()[0].numpy(),
        "shape": shape.detach()[0].numpy(),
        "angles": np.zeros(model.num_dofs, np.float32),
        "global_orient": np.zeros(3, np.float32),
        "transl": transl.detach()[0].numpy(),
        "displacement": disp.astype(np.float32),
    }
    return {k: np.asarray(v, dtype=np.float32) for k, v in reg.items()}, {"fit_mean_mm": err}


@lru_cache(maxsize=1)
def _population() -> Any:
    from anny.shape_distribution import SimpleShapeDistribution

    return SimpleShapeDistribution(_anny())


@dataclass(frozen=True)
class Population:
    """Who Anny's people are: ages in years and the share of children.

    A person is a child with probability ``children`` and then aged uniformly in ``child_age``,
    else an adult aged uniformly in ``age``. The defaults -- adults 18 to 80, one person in ten a
    child of 5 to 17, no infant or toddler -- are a design choice for scenes of people standing,
    walking and playing sport, not a census (docs/population.md has the histogram). Anny's own
    population, ages uniform over 0 to 90 (infants included), is ``Population.ANNY``. The age is
    Anny's morphological age, calibrated on WHO height-for-age data; height, weight, muscle and
    proportions follow from it (:func:`sample_phenotype`).
    """

    age: tuple[float, float] = (18.0, 80.0)
    children: float = 0.1
    child_age: tuple[float, float] = (5.0, 17.0)

    def __post_init__(self) -> None:
        for name, (lo, hi) in (("age", self.age), ("child_age", self.child_age)):
            if not 0.0 <= lo <= hi <= 90.0:
                raise ValueError(f"{name} must be [low, high] years with 0 <= low <= high <= 90, got {[lo, hi]}")
        if not 0.0 <= self.children <= 1.0:
            raise ValueError(f"children must be a share in [0, 1], got {self.children}")

    def distribution(self) -> Any:
        """The age distribution in the form Anny's ``SimpleShapeDistribution`` samples from."""
        adult = torch.distributions.Uniform(torch.tensor(self.age[0], dtype=torch.float64),
                                            torch.tensor(self.age[1], dtype=torch.float64))
        if self.children == 0.0:
            return adult  # draws exactly as Anny's default Uniform(0, 90) when age is (0, 90)
        child = torch.distributions.Uniform(torch.tensor(self.child_age[0], dtype=torch.float64),
                                            torch.tensor(self.child_age[1], dtype=torch.float64))
        return _AgeMixture(adult, child, self.children)


Population.ANNY = Population(age=(0.0, 90.0), children=0.0)  # type: ignore[attr-defined]


class _AgeMixture:
    """Adult ages or, with probability ``share``, child ages (a ``sample(shape)`` like torch's)."""

    def __init__(self, adult: Any, child: Any, share: float) -> None:
        self.adult, self.child, self.share = adult, child, share

    def sample(self, shape: tuple[int, ...]) -> torch.Tensor:
        is_child = torch.rand(shape, dtype=torch.float64) < self.share
        return torch.where(is_child, self.child.sample(shape), self.adult.sample(shape))


@lru_cache(maxsize=8)
def _population(population: Population = Population.ANNY) -> Any:  # type: ignore[attr-defined]
    from anny.shape_distribution import SimpleShapeDistribution

    return SimpleShapeDistribution(_anny(), morphological_age_distribution=population.distribution())


def sample_phenotype(rng: np.random.Generator, population: Population | None = None) -> dict[str, float]:
    """Anny phenotype values in [0, 1] for one person of a population, and their age.

    Anny's population model (``anny.shape_distribution.SimpleShapeDistribution``, calibrated on
    WHO height-for-age data) with the ages of ``population`` (default :class:`Population`: adults
    18-80 and 10 % children of 5-17); sex uniform, then height, weight, muscle and proportions from
    Beta distributions conditioned on age and sex. Uniform phenotype values would make Anny's
    extremes (a 2.3 m man) as common as the middle. Seeded from ``rng`` only (torch's global
    generator is forked, not touched).

    Returns:
        ``gender``, ``age``, ``muscle``, ``weight``, ``height``, ``proportions`` (Anny's values in
        [0, 1]) and ``age_years``.
    """
    population = Population() if population is None else population
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(rng.integers(2**62)))
        years, ph = _population(population).sample(1)
    out = {k: float(v.reshape(-1)[0]) for k, v in ph.items()}
    out["age_years"] = float(years.reshape(-1)[0])
    return out


def anny_subject(
    model: BLSM, subject_id: str, rng: np.random.Generator, texture_size: int = 1024,
    population: Population | None = None, detail: bool = False, detail_seed: int = 0,
) -> Subject:
    """A person sampled from Anny as a stand-in scan: mesh, procedural texture, registration, rig.

    Args:
        model: the BLSM model (the registration's model).
        subject_id: the subject's name.
        rng: the random generator (phenotype and outfit come from it only).
        texture_size: albedo texture size in texels.
        population: ages of the people (default :class:`Population`).
        detail: paint face, skin and hand detail (:mod:`synth.skin_detail`; it closes the empty eye
            sockets with eyeballs), drawn from its own generator, seeded by ``detail_seed`` and the
            id; off, the subject is the same as without this option.
    """
    from blsm.build_anny import ANNY_TO_WORLD, barycentric_interpolate
    from synth import textures

    tri, bary = _anny_embedding(model)
    am = _anny()
    pheno = sample_phenotype(rng, population)
    with torch.no_grad():
        coeffs = am.get_phenotype_blendshape_coefficients(
            **{k: torch.tensor([pheno[k]], dtype=torch.float64) for k in am.phenotype_labels}
        )
        verts = am.get_rest_vertices(coeffs)[0].numpy() @ ANNY_TO_WORLD.T
    faces = am.faces.numpy()
    target = barycentric_interpolate(verts, faces, tri, bary)
    reg, fit = fit_registration(model, target)
    # Put the scan where the registration is (Anny's origin is not BLSM's).
    uv = am.texture_coordinates.numpy()
    faces_uv = am.face_texture_coordinate_indices.numpy()
    with torch.no_grad():
        reg_verts, _, out = registration_output(model, reg)
    outfit = textures.sample_outfit(rng)
    bones = paint_weights(verts, reg_verts.numpy(), model.weights.numpy(), faces, model.faces.numpy()).argmax(1)
    cuts: dict[str, float] = {}
    spec = None
    if detail:
        from synth.skin_detail import FACE_POINTS, subject_detail

        with torch.no_grad():
            kp = model._keypoints(reg_verts[None], out.joints)[0].numpy()
        points = {k: kp[model.keypoint_names.index(k)] for k in FACE_POINTS}
        verts, spec = subject_detail(detail_seed, subject_id, verts, faces, bones, list(model.bone_names),
                                     points, outfit.skin, outfit.hair, pheno)  # fmt: skip
    texture = textures.make_albedo(
        uv, faces_uv, verts, faces, bones, list(model.bone_names), out.joints[0].numpy(), outfit, rng, texture_size,
        cuts_out=cuts, detail=spec,
    )
    meta = {
        "source": "anny",
        "anny_version": getattr(__import__("anny"), "__version__", "?"),
        "phenotype": pheno,
        "outfit": outfit.to_json(),
        "outfit_cuts": cuts,  # the painted garments' borders (synth.garments cuts its cloth there)
        "registration": fit,
        "height_m": float(verts[:, 1].max() - verts[:, 1].min()),
    }
    if spec is not None:
        meta["detail"] = spec.to_json()
    return rig_subject(model, subject_id, verts, faces, uv, faces_uv, texture, reg, meta)
