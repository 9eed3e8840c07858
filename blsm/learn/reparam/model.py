"""A whole BLSM model reparameterised to a new template (thesis ch. 3, Eqs. 3.5-3.7).

:func:`reparameterise` takes a model file's data and a new template mesh and returns the data of a
model in the new topology, written by :func:`blsm.io.save_model` and loaded by :func:`blsm.load`:

==========================  =====================================================================
template                    mu_2: the new template, aligned to the old surface (Sec. 3.3.2;
                            :func:`blsm.learn.reparam.mapping.align_template`)
faces, uvs, faces_uv        the new mesh; UVs interpolated from the old ones (below)
shape_basis                 ``mapped`` (default): ``W P_s`` (Eq. 3.6 applied to the shape basis;
                            the model's covariance is ``W Sigma_1 W^T``, the first term of Eq. 3.5,
                            and every shape coefficient keeps its meaning), or ``eq35``: the K + 1
                            principal components of Eq. 3.5 (:func:`shape_space_eq35`), with the
                            population's coefficients mapped exactly (``c_2 = A c + a``)
bone_correctives            ``W P_bc`` (Eq. 3.6)
weights                     ``W' B_1`` (Eq. 3.7), renormalised to rows summing to 1
vertex_parts                the part of the corner with the largest barycentric
vertex_bones                the bone of largest new weight (the file format's definition)
vertex_mirror               the nearest new vertex to each vertex mirrored across x = 0
keypoint_vertices/weights   surface keypoints: the closest point on the new surface of the old
                            keypoint on the old template; joint keypoints carried over
heads, frames, bone_*       carried over (the skeleton does not depend on the topology)
population_*                bone unchanged; shape unchanged (``mapped``) or mapped (``eq35``)
==========================  =====================================================================

Extra arrays (ignored by :func:`blsm.io.read_model`, read by :func:`read_correspondence`):
``reparam_corners`` (N2, 3) int32 old vertex indices and ``reparam_bary`` (N2, 3) float32: row i of
W'; ``reparam_distance`` (N2,) float32 metres from each new vertex to the old surface.

**UVs.** A new vertex takes the old UVs interpolated at its correspondence. A new face whose
corners' correspondences lie in different UV charts (old faces connected through shared UV
indices) straddles a seam of the old atlas: every corner outside the chart of the face's centre
takes the UV of its closest point on the old surface *inside* that chart. A corner on the seam
itself gets its exact UV on the centre's side; one beyond it is clamped to the seam (the nearest
point of the chart; ``clamped_corners`` in the report, against ``corners_off_chart``), so no face
spans two charts of the atlas.

Bad templates raise ``ValueError`` naming the file: empty, or not covering the body (more than
``far_fraction`` of the new vertices farther than ``far_distance`` from the old surface, or more
than ``uncovered_fraction`` of the old vertices farther than ``far_distance`` from the new one).
"""

from __future__ import annotations

import datetime
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from blsm import io
from blsm.learn.reparam.mapping import (
    ALIGN_MODES,
    Correspondence,
    align_template,
    apply_basis,
    apply_rows,
    closest_points,
    mapping_matrix,
    mirror_map,
    shape_space_eq35,
)

SHAPE_SPACES = ("mapped", "eq35")


@dataclass
class ReparamConfig:
    """Settings of :func:`reparameterise`.

    Attributes:
        align: ``auto``, ``none``, ``rigid`` or ``similarity`` (:func:`align_template`).
        shape_space: ``mapped`` or ``eq35`` (module docstring).
        far_distance: metres; a correspondence farther than this is "far" (default 1 cm).
        far_fraction: largest allowed fraction of new vertices that are far from the old surface.
        uncovered_fraction: largest allowed fraction of old vertices far from the new surface.
    """

    align: str = "auto"
    shape_space: str = "mapped"
    far_distance: float = 0.01
    far_fraction: float = 0.01
    uncovered_fraction: float = 0.01

    def __post_init__(self) -> None:
        if self.align not in ALIGN_MODES:
            raise ValueError(f"align must be one of {ALIGN_MODES}, got {self.align!r}")
        if self.shape_space not in SHAPE_SPACES:
            raise ValueError(f"shape_space must be one of {SHAPE_SPACES}, got {self.shape_space!r}")
        if self.far_distance <= 0 or not 0 <= self.far_fraction < 1 or not 0 <= self.uncovered_fraction < 1:
            raise ValueError("far_distance must be > 0, far_fraction and uncovered_fraction in [0, 1)")


def read_template(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The vertices (N, 3) float64 and triangles (F, 3) int64 of an OBJ / PLY / OFF / STL mesh.

    Read by trimesh with ``process=False`` (the file's vertex order is kept; an OBJ with texture
    coordinates may be split at its seams by trimesh). Errors name the file.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such template file")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many kinds on a bad file
        raise ValueError(f"{path}: not a readable mesh ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None
    v = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64)
    f = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64)
    if len(v) == 0 or len(f) == 0:
        raise ValueError(f"{path}: empty template ({len(v)} vertices, {len(f)} faces)")
    if not np.isfinite(v).all():
        raise ValueError(f"{path}: template has NaN or infinite vertices")
    return v, f


def subdivide_template(vertices: np.ndarray, faces: np.ndarray, levels: int, scheme: str = "loop"):
    """The model's template subdivided ``levels`` times: ``loop`` (trimesh's Loop scheme, the
    smooth subdivision surface; it shrinks the surface slightly) or ``midpoint`` (every triangle
    into four, new vertices at edge midpoints: exactly on the old surface).

    Returns:
        (vertices (N2, 3), faces (F2, 3)); the old vertices come first in the same order.
    """
    import trimesh.remesh as rm

    if levels < 1:
        raise ValueError(f"subdivide must be >= 1, got {levels}")
    if scheme == "loop":
        v, f = rm.subdivide_loop(vertices, faces, iterations=levels)
    elif scheme == "midpoint":
        v, f = vertices, faces
        for _ in range(levels):
            v, f = rm.subdivide(v, f)
    else:
        raise ValueError(f"scheme must be loop or midpoint, got {scheme!r}")
    return np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)


def check_coverage(corr: Correspondence, back: Correspondence, cfg: ReparamConfig, where: str) -> dict:
    """Raise ``ValueError`` naming ``where`` when the new template does not cover the body.

    Args:
        corr: new vertices on the old surface; back: old vertices on the new surface.

    Returns:
        The statistics (mm, fractions) for the report.
    """
    far = float((corr.distance > cfg.far_distance).mean())
    unc = float((back.distance > cfg.far_distance).mean())
    mm = 1000 * cfg.far_distance
    if far > cfg.far_fraction:
        raise ValueError(f"{where}: {100 * far:.1f} % of the template's vertices are more than {mm:g} mm from "
                         f"the model's surface (at most {100 * cfg.far_fraction:g} % allowed): not a template of "
                         "this body, or not aligned to it")
    if unc > cfg.uncovered_fraction:
        raise ValueError(f"{where}: the template does not cover the body: {100 * unc:.1f} % of the model's "
                         f"vertices are more than {mm:g} mm from it (at most {100 * cfg.uncovered_fraction:g} % allowed)")
    return {
        "new_to_old_mm": {"mean": 1000 * float(corr.distance.mean()), "max": 1000 * float(corr.distance.max())},
        "old_to_new_mm": {"mean": 1000 * float(back.distance.mean()), "max": 1000 * float(back.distance.max())},
        "far_fraction": far, "uncovered_fraction": unc,
        "coincident_fraction": float((corr.distance < 1e-4).mean()),
    }


def reparameterise(
    data: io.ModelData, vertices: np.ndarray, faces: np.ndarray, cfg: ReparamConfig | None = None,
    where: str = "template",
) -> tuple[io.ModelData, dict]:
    """Reparameterise a model to a new template (thesis ch. 3; module docstring for every array).

    Args:
        data: the model file's data (:func:`blsm.io.read_model`).
        vertices: (N2, 3) new template, metres, in (or near) the model's frame; faces: (F2, 3).
        cfg: :class:`ReparamConfig`.
        where: the template's name (file) for error messages.

    Returns:
        (model data for :func:`blsm.io.save_model`, with the extra ``reparam_*`` arrays; a report).
    """
    cfg = cfg or ReparamConfig()
    a = data.arrays
    v1, f1 = np.asarray(a["template"], np.float64), np.asarray(a["faces"], np.int64)
    faces = np.asarray(faces, dtype=np.int64)
    if len(vertices) == 0 or len(faces) == 0:
        raise ValueError(f"{where}: empty template ({len(vertices)} vertices, {len(faces)} faces)")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"{where}: faces must be (F, 3) indices into the {len(vertices)} vertices")
    mu2, transform, align_rep, corr = align_template(vertices, v1, f1, cfg.align)
    back = closest_points(v1, mu2, faces)
    report: dict[str, Any] = {"alignment": align_rep, "transform": transform.tolist(),
                              "coverage": check_coverage(corr, back, cfg, where)}
    wp = mapping_matrix(corr, len(v1))
    arrays: dict[str, np.ndarray] = {"template": mu2.astype(np.float32), "faces": faces.astype(np.int32)}
    arrays.update(_uv_arrays(a, corr, mu2, faces, v1, f1, report))
    weights = np.clip(apply_rows(wp, a["weights"]), 0.0, None)  # Eq. 3.7
    weights /= weights.sum(1, keepdims=True)
    arrays["weights"] = weights.astype(np.float32)
    for k in ("heads", "frames", "bone_mean", "bone_basis", "population_bone", "keypoint_joint"):
        arrays[k] = np.array(a[k])
    arrays["bone_correctives"] = apply_basis(wp, a["bone_correctives"]).astype(np.float32)  # Eq. 3.6
    basis1 = np.asarray(a["shape_basis"], np.float64)
    if cfg.shape_space == "mapped":
        arrays["shape_basis"] = apply_basis(wp, basis1).astype(np.float32)
        arrays["population_shape"] = np.array(a["population_shape"])
    else:
        space = shape_space_eq35(wp, v1, basis1, mu2)  # Eq. 3.5
        arrays["shape_basis"] = space.components.astype(np.float32)
        pop = np.asarray(a["population_shape"], np.float64)
        arrays["population_shape"] = (pop @ space.coeff_map.T + space.coeff_offset).astype(np.float32)
        report["eq35"] = {"components": len(space.variances), "variance_m2": space.variances.tolist(),
                          "coeff_map": space.coeff_map.tolist(), "coeff_offset": space.coeff_offset.tolist()}
    dominant = corr.corners[np.arange(len(mu2)), corr.bary.argmax(1)]
    arrays["vertex_parts"] = np.asarray(a["vertex_parts"])[dominant].astype(np.int32)
    arrays["vertex_bones"] = weights.argmax(1).astype(np.int32)
    arrays["vertex_mirror"], mirror_err = mirror_map(mu2)
    report["mirror_max_mm"] = 1000 * mirror_err
    arrays["keypoint_vertices"], arrays["keypoint_weights"], kp_err = _keypoints(a, v1, mu2, faces)
    report["keypoint_offset_mm"] = kp_err
    arrays["reparam_corners"] = corr.corners.astype(np.int32)
    arrays["reparam_bary"] = corr.bary.astype(np.float32)
    arrays["reparam_distance"] = corr.distance.astype(np.float32)
    meta = dict(data.meta)
    if meta.pop("shape_decoder", None) is not None:  # a non-linear decoder (Eq. 11) is not mapped
        report["dropped_shape_decoder"] = True
    meta["name"] = f"{data.meta.get('name', 'blsm')}-reparam"
    meta["built"] = datetime.date.today().isoformat()
    meta["reparam"] = {
        "source_model": str(data.path) if data.path is not None else None,
        "source_sha256": io.sha256_file(data.path) if data.path is not None and Path(data.path).is_file() else None,
        "template": where, "source_vertices": len(v1), "vertices": len(mu2), "config": asdict(cfg),
        **report,  # with eq35: the coefficient map c_2 = A c + a of the source's coefficients
    }
    return io.ModelData(arrays=arrays, meta=meta, dof_table_yaml=data.dof_table_yaml), report


def _keypoints(a: dict, v1: np.ndarray, v2: np.ndarray, f2: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Surface keypoints re-expressed on the new surface (closest point of the old keypoint); joint
    keypoints (``keypoint_joint >= 0``) keep their joint and get the same kind of placeholder."""
    kv, kw = np.asarray(a["keypoint_vertices"]), np.asarray(a["keypoint_weights"], np.float64)
    pts = np.einsum("kc,kcd->kd", kw, v1[kv])
    c = closest_points(pts, v2, f2)
    surf = np.asarray(a["keypoint_joint"]) < 0
    worst = float(c.distance[surf].max()) * 1000 if surf.any() else 0.0
    return c.corners.astype(np.int32), c.bary.astype(np.float32), worst


def _uv_arrays(a, corr: Correspondence, v2, f2, v1, f1, report: dict) -> dict[str, np.ndarray]:
    """``uvs`` and ``faces_uv`` of the new mesh (module docstring: seams take the nearest corner)."""
    uvs1, fuv1 = np.asarray(a["uvs"], np.float64), np.asarray(a["faces_uv"], np.int64)
    n_f1 = len(f1)
    # UV charts: old faces connected through shared UV indices.
    adj = sp.csr_matrix((np.ones(fuv1.size), (np.repeat(np.arange(n_f1), 3), fuv1.ravel())), shape=(n_f1, len(uvs1)))
    _, chart = connected_components(adj @ adj.T, directed=False)
    corner_uv = np.einsum("nk,nkc->nc", corr.bary, uvs1[fuv1[corr.face]])  # (N2, 2) per new vertex
    centre = closest_points(v2[f2].mean(1), v1, f1)
    home = chart[centre.face]  # (F2,) chart of each new face's centre
    uv = corner_uv[f2]  # (F2, 3, 2)
    off = chart[corr.face][f2] != home[:, None]  # (F2, 3) corners in another chart
    stretched = 0
    for h in np.unique(home[off.any(1)]):
        g, k = np.nonzero(off & (home == h)[:, None])
        mine = np.flatnonzero(chart == h)
        c = closest_points(v2[f2[g, k]], v1, f1[mine])  # the nearest point inside the home chart
        uv[g, k] = np.einsum("nk,nkc->nc", c.bary, uvs1[fuv1[mine[c.face]]])
        stretched += int((c.distance > corr.distance[f2[g, k]] + 1e-6).sum())
    flat = np.round(uv.reshape(-1, 2), 7)
    uvs2, inverse = np.unique(flat, axis=0, return_inverse=True)
    report["uv"] = {"charts": int(chart.max() + 1), "corners_off_chart": int(off.sum()), "clamped_corners": stretched}
    return {"uvs": uvs2.astype(np.float32), "faces_uv": inverse.reshape(-1, 3).astype(np.int32)}


def read_correspondence(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """W' of a reparameterised model file: (corners (N2, 3) old vertex indices, bary (N2, 3)).

    Raises:
        ValueError: naming the file when it is not a model written by :func:`reparameterise`.
    """
    raw = io.read_versioned_npz(path, io.FORMAT, io.FORMAT_VERSION, "model")
    if "reparam_corners" not in raw or "reparam_bary" not in raw:
        raise ValueError(f"{path}: not a reparameterised model (no reparam_corners / reparam_bary; "
                         "make one with blsm reparam)")
    corners, bary = np.asarray(raw["reparam_corners"], np.int64), np.asarray(raw["reparam_bary"], np.float64)
    if corners.shape != bary.shape or corners.ndim != 2 or corners.shape[1] != 3:
        raise ValueError(f"{path}: reparam_corners / reparam_bary must both be (N2, 3)")
    return corners, bary
