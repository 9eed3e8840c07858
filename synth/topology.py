"""People's vertices in a second mesh topology (``labels.topology``; thesis ch. 3 via ``blsm reparam``).

With ``labels: {topology: MODEL2.npz, topology_name: NAME}`` every sample gets the member
``vertices_<NAME>.npy.gz``: (P, V2, 3) float32, world metres, one row per person in mask order, the
person's registered body in the topology of ``MODEL2`` (a model written by ``blsm reparam``, e.g.
the Loop-subdivided template) and in the sample's pose.

How: the reparameterised model with the *same* parameters as the sample's person (pose x,
``global_orient``, ``transl``, and the subject's bone and shape coefficients), plus the subject's
per-vertex displacement mapped by W' (Eq. 3.6 for a per-vertex offset), skinned with the new
weights (Eq. 3.7) -- exactly what :func:`synth.subjects.registration_output` does with the original
model, so ``keypoints_3d`` and these vertices describe the same body. Not ``W'`` applied to the
posed old vertices: that is a point on the old, faceted surface; the reparameterised model keeps
the new template's own surface (a Loop subdivision's smoothness) and skins each new vertex with its
own weights. The two differ by the new template's offset from the old surface and by LBS's
non-linearity across a triangle (docs/reparam.md, "Pose check"). Needs a posable pipeline
(``rigged`` or ``blsm``); with ``rigged`` it is the registered BLSM body (as the keypoints are), not
the painted rig that is rendered.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch


def member(name: str) -> str:
    """The sample member holding topology ``name``'s vertices."""
    return f"vertices_{name}.npy.gz"


class Topology:
    """A reparameterised model and its W' (:func:`blsm.learn.reparam.model.read_correspondence`)."""

    def __init__(self, path: str | Path, name: str, model: Any) -> None:
        """``model``: the generator's (original) BLSM; the file must be reparameterised from its topology."""
        import blsm
        from blsm.learn.reparam.model import read_correspondence

        self.name, self.path = name, Path(path)
        corners, bary = read_correspondence(self.path)
        self.model = blsm.load(self.path)
        if corners.max() >= model.num_vertices or self.model.bone_names != model.bone_names:
            raise ValueError(f"{self.path}: not reparameterised from the generator's model "
                             f"({model.num_vertices} vertices, its bones)")
        if self.model.num_shape_coeffs != model.num_shape_coeffs:
            raise ValueError(f"{self.path}: {self.model.num_shape_coeffs} shape coefficients, the generator's model has "
                             f"{model.num_shape_coeffs} (make it with blsm reparam --shape-space mapped)")
        self.corners = torch.as_tensor(corners)
        self.bary = torch.as_tensor(bary, dtype=torch.float32)

    @torch.no_grad()
    def vertices(self, registration: dict[str, np.ndarray], pose: np.ndarray, global_orient: np.ndarray,
                 transl: np.ndarray) -> np.ndarray:
        """(V2, 3) float32: the subject's registered body in this topology and pose (module docstring).

        Args:
            registration: the subject's ``bone``, ``shape``, ``displacement`` (Vb, 3) (:class:`synth.subjects.Subject`).
            pose: (47,) unconstrained values x; global_orient: (3,) axis-angle; transl: (3,) metres.
        """
        from synth.subjects import registration_output

        disp = torch.as_tensor(np.asarray(registration["displacement"]), dtype=torch.float32)
        mapped = (self.bary[..., None] * disp[self.corners]).sum(1)  # W' D (Eq. 3.6)
        reg = {"bone": registration["bone"], "shape": registration["shape"], "displacement": mapped.numpy()}
        v, _, _ = registration_output(self.model, reg, pose, global_orient=global_orient, transl=transl)
        return v.numpy().astype(np.float32)
