"""The mesh hierarchy of the spiral networks: levels and spirals of a template (thesis Sec. 4.3.2).

:func:`mesh_hierarchy` down-samples a mesh by quadric edge collapse (:func:`blsm.spiral.sampling.build_levels`;
``factors`` 4, 2, 2, 2 give paper 000's up-sampling factors 2, 2, 2, 4 read from coarse to fine) and
builds the spiral sequences of every level (:func:`blsm.spiral.sequences.spiral_sequences`, Eq. 10 /
thesis Eq. 4.3) with the level's ring count (Table 4.1's kernel size) and fixed length. For a BLSM
model the mesh is its template posed in :data:`REFERENCE_ANGLES` (:func:`reference_angles`; thesis
Fig. 4.2: elbows, knees, hips, shoulders, wrists and ankles bent, so that the collapse keeps vertices
around the joints). ``recovery.mesh.operators`` caches this per model file and adds a keypoint
regressor; :mod:`blsm.spiral.shape` stores it in a model file.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from blsm.spiral.sampling import Level, build_levels
from blsm.spiral.sequences import spiral_sequences

REFERENCE_ANGLES: dict[str, float] = {
    "shoulder_l.abduct": 0.8, "shoulder_r.abduct": 0.8, "shoulder_l.flex": 0.4, "shoulder_r.flex": 0.4,
    "elbow_l.flex": 1.2, "elbow_r.flex": 1.2, "wrist_l.flex": 0.5, "wrist_r.flex": 0.5,
    "hip_l.flex": 0.6, "hip_r.flex": 0.6, "hip_l.abduct": 0.3, "hip_r.abduct": 0.3,
    "knee_l.flex": 1.0, "knee_r.flex": 1.0, "ankle_l.plantarflex": 0.3, "ankle_r.plantarflex": 0.3,
    "spine_02.flex": 0.2, "neck.flex": 0.3,
}
"""The reference pose of the down-sampling (radians, each clamped to 90 % of its limit; sign
towards the limit of the larger magnitude): bent limbs curve the surface at the joints, so the
quadric error keeps vertices there (thesis Fig. 4.2)."""


@dataclass(frozen=True)
class MeshOpsSettings:
    """How the operators are built (part of the cache key).

    Attributes:
        factors: vertex reduction per level (thesis: 4, 2, 2, 2).
        rings: spiral rings per convolution level 0..len(factors)-1 (Table 4.1 kernel sizes 2, 1, 1, 1).
        lengths: fixed spiral length per level (1 + the rings' typical vertex count; padded with -1).
        regressor_samples: posed bodies the joint regressor is fitted on.
        regressor_support: candidate vertices per joint (nearest on the rest template, on the
            joint's bone, its parent and its children).
    """

    factors: tuple[float, ...] = (4, 2, 2, 2)
    rings: tuple[int, ...] = (2, 1, 1, 1)
    lengths: tuple[int, ...] = (25, 9, 9, 9)
    regressor_samples: int = 400
    regressor_support: int = 128

    def __post_init__(self) -> None:
        # one type per field, so that a config read back from a checkpoint (factors 4.0) keys the same cache as YAML's 4
        object.__setattr__(self, "factors", tuple(float(f) for f in self.factors))
        object.__setattr__(self, "rings", tuple(int(r) for r in self.rings))
        object.__setattr__(self, "lengths", tuple(int(n) for n in self.lengths))
        object.__setattr__(self, "regressor_samples", int(self.regressor_samples))
        object.__setattr__(self, "regressor_support", int(self.regressor_support))
        if not (len(self.rings) == len(self.lengths) == len(self.factors)):
            raise ValueError("factors, rings and lengths need one entry per level")
        if min(self.rings) < 1 or min(self.lengths) < 1 or min(self.factors) <= 1:
            raise ValueError("rings and lengths must be >= 1 and factors > 1")


@dataclass
class MeshOperators:
    """Everything the spiral networks need about the template (module docstring).

    Attributes:
        levels: the down/up-sampling steps (``len(factors)`` of them).
        spirals: spiral indices per level 0..len(factors)-1, (n_l, L_l), -1 = padding.
        faces: triangles per level 0..len(factors) (level 0 is the template's).
        reference: (V, 3) the template in the reference pose (metres).
        regressor: (K, V) keypoints = regressor @ vertices.
        keypoint_names: the K names (the model's).
        regressor_error_mm: the joint regressor's mean error on held-out posed bodies.
        model_sha256: the model file these were made for.
    """

    levels: list[Level]
    spirals: list[np.ndarray]
    faces: list[np.ndarray]
    reference: np.ndarray
    regressor: np.ndarray
    keypoint_names: list[str]
    regressor_error_mm: float
    model_sha256: str

    @property
    def sizes(self) -> list[int]:
        """Vertices per level 0..len(levels)."""
        return [len(self.reference)] + [len(lv.down) for lv in self.levels]


def reference_angles(body: torch.nn.Module) -> torch.Tensor:
    """(47,) the reference pose of :data:`REFERENCE_ANGLES`, inside the model's limits."""
    lim = body.dof_limits.double()
    out = torch.zeros(body.num_dofs, dtype=torch.float64)
    for name, value in REFERENCE_ANGLES.items():
        if name not in body.dof_names:
            continue
        i = body.dof_names.index(name)
        lo, hi = float(lim[i, 0]), float(lim[i, 1])
        sign = 1.0 if abs(hi) >= abs(lo) else -1.0
        out[i] = min(value, 0.9 * max(abs(lo), abs(hi))) * sign
    return out.clamp(lim[:, 0] * 0.9, lim[:, 1] * 0.9)


def mesh_hierarchy(positions: np.ndarray, faces: np.ndarray, settings: MeshOpsSettings) -> MeshOperators:
    """Levels and spirals of any mesh (no keypoint regressor: an empty (0, V) one)."""
    ref = np.asarray(positions, dtype=np.float64)
    faces0 = np.asarray(faces, dtype=np.int64)
    levels = build_levels(ref, faces0, tuple(settings.factors))
    pos, fcs, spirals, all_faces = ref, faces0, [], [faces0]
    for i, lv in enumerate(levels):
        spirals.append(spiral_sequences(pos, fcs, settings.rings[i], settings.lengths[i]))
        pos, fcs = pos[lv.down], lv.faces
        all_faces.append(fcs)
    return MeshOperators(levels=levels, spirals=spirals, faces=all_faces, reference=ref.astype(np.float32),
                         regressor=np.zeros((0, len(ref)), np.float32), keypoint_names=[],
                         regressor_error_mm=0.0, model_sha256="")


def body_hierarchy(body: torch.nn.Module, settings: MeshOpsSettings) -> MeshOperators:
    """The hierarchy of a :class:`blsm.BLSM`'s template posed in :func:`reference_angles` (no keypoint
    regressor; ``recovery.mesh.operators.build_operators`` adds one)."""
    with torch.no_grad():
        ref = body(angles=reference_angles(body)[None].to(body.template.dtype)).vertices[0].double().cpu().numpy()
    return mesh_hierarchy(ref, body.faces.cpu().numpy(), settings)
