"""Stage 1 of the scan registration: the landmark fit (thesis Eq. 5.13), batched over scans.

Joint angles theta (through the unconstrained x of Eq. 5.6, so the limits always hold), per-bone
global scales b (through log b, so they stay positive), global orientation and translation minimise
the landmark distances of the posed template. The global rigid motion is initialised by Procrustes
on the trunk landmarks, then L-BFGS refines everything. With ``shape_init`` (an engineering
addition, not in the thesis) the initial model's shape coefficients are fitted too.

The template landmarks, the selection operator A_lm of Eqs. 5.13 and 5.15, are a
:class:`LandmarkSelection`: the packaged set (:func:`default_selection`) or a YAML file
(:func:`read_landmark_definitions`).

Units and conventions: metres, radians, Y up, the body faces +Z at rest, +X is the body's left.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from blsm.io import read_yaml
from blsm.joint_limits import unconstrained_from_angles
from blsm.learn.posing import pose
from blsm.learn.registration.register_config import RegisterConfig

# Bones whose landmarks fix the global rigid motion before the articulated fit.
TRUNK_BONES: tuple[str, ...] = ("pelvis", "spine_01", "spine_02", "spine_03", "hip_l", "hip_r")


# ------------------------------------------------------------------------------------------------
# The template landmarks A_lm


@dataclass
class LandmarkSelection:
    """The selection operator A_lm of Eqs. 5.13 and 5.15: named points on the template surface.

    Attributes:
        names: the L landmark names.
        vertices: (L, 3) template vertex indices of each point's triangle (or the vertex thrice).
        bary: (L, 3) barycentric weights, rows sum to 1.
    """

    names: list[str]
    vertices: torch.Tensor
    bary: torch.Tensor

    @classmethod
    def from_index(cls, names: Sequence[str], index: Any, faces: torch.Tensor | None = None,
                   bary: Any = None) -> LandmarkSelection:
        """Build from (L,) vertex indices, or from (L,) face indices with (L, 3) barycentrics."""
        idx = torch.as_tensor(np.asarray(index), dtype=torch.long)
        names = [str(n) for n in names]
        if idx.dim() != 1 or idx.shape[0] != len(names):
            raise ValueError(f"landmark index must be (L,) with L = {len(names)} names, got {tuple(idx.shape)}")
        if bary is None:
            return cls(names, idx[:, None].expand(-1, 3).clone(), torch.tensor([[1.0, 0.0, 0.0]]).expand(len(names), 3).clone())
        if faces is None:
            raise ValueError("face landmarks need the model's faces")
        w = torch.as_tensor(np.asarray(bary), dtype=torch.float32)
        if w.shape != (len(names), 3):
            raise ValueError(f"landmark bary must be (L, 3), got {tuple(w.shape)}")
        return cls(names, faces[idx].long(), w)

    def __len__(self) -> int:
        return len(self.names)

    def select(self, points: torch.Tensor) -> torch.Tensor:
        """A_lm: (B, V, 3) mesh vertices -> (B, L, 3) landmark positions."""
        w = self.bary.to(points.dtype)
        return (points[:, self.vertices] * w[..., None]).sum(2)


def default_selection(model) -> LandmarkSelection:
    """The packaged landmark set (``blsm.learn.scans.format.template_landmarks``)."""
    try:
        from blsm.learn.scans.format import template_landmarks
    except ImportError as exc:
        raise ValueError("no landmark selection given and blsm.learn.scans.format is not available") from exc
    names, index, bary = template_landmarks(model)  # (L,), (L, 3) vertices, (L, 3) weights
    return LandmarkSelection(list(names), torch.as_tensor(index).long(), torch.as_tensor(bary).float())


def read_landmark_definitions(path: str | Path, model) -> LandmarkSelection:
    """Read template landmarks from YAML: ``name: {vertex: i}`` or ``name: {face: f, bary: [a, b, c]}``.

    A top-level ``landmarks:`` mapping is also accepted.
    """
    path = Path(path)
    data = read_yaml(path, "landmark definitions")
    if isinstance(data, dict) and isinstance(data.get("landmarks"), dict):
        data = data["landmarks"]
    if not isinstance(data, dict) or not data:
        raise ValueError(f"{path}: expected a mapping name -> {{vertex: i}} or {{face: f, bary: [a, b, c]}}")
    names, verts, bary = [], [], []
    nv, nf = model.num_vertices, int(model.faces.shape[0])
    for name, spec in data.items():
        if not isinstance(spec, dict):
            raise ValueError(f"{path}: {name}: expected {{vertex: i}} or {{face: f, bary: [a, b, c]}}")
        if "vertex" in spec and isinstance(spec["vertex"], int) and 0 <= spec["vertex"] < nv:
            verts.append([spec["vertex"]] * 3)
            bary.append([1.0, 0.0, 0.0])
        elif "face" in spec and isinstance(spec["face"], int) and 0 <= spec["face"] < nf \
                and isinstance(spec.get("bary"), list) and len(spec["bary"]) == 3:
            verts.append(model.faces[spec["face"]].tolist())
            bary.append([float(b) for b in spec["bary"]])
        else:
            raise ValueError(f"{path}: {name}: bad landmark {spec!r} (vertex in [0, {nv}) or face in [0, {nf}) + bary)")
        names.append(str(name))
    return LandmarkSelection(names, torch.tensor(verts, dtype=torch.long), torch.tensor(bary, dtype=torch.float32))


# ------------------------------------------------------------------------------------------------
# The fit (Eq. 5.13)


@dataclass
class Stage1:
    """Result of :func:`fit_landmarks` (Eq. 5.13), batched.

    Attributes:
        bone_scales: (B, J) global bone scales b. angles: (B, 47) radians.
        global_orient: (B, 3) axis-angle. transl: (B, 3) metres.
        landmark_error: (B,) RMS landmark distance in metres over the located landmarks.
        shape: (B, Ks) the initial model's shape coefficients (zeros without ``shape_init``).
        shape_offsets: (B, V, 3) their T-pose offsets V_s (Eq. 8), metres.
    """

    bone_scales: torch.Tensor
    angles: torch.Tensor
    global_orient: torch.Tensor
    transl: torch.Tensor
    landmark_error: torch.Tensor
    shape: torch.Tensor | None = None
    shape_offsets: torch.Tensor | None = None


def pose_angles(model, x: torch.Tensor) -> torch.Tensor:
    """Eq. 5.6: (B, 47) unconstrained values -> angles in radians inside the model's limits."""
    from blsm.joint_limits import angles_from_unconstrained

    return angles_from_unconstrained(x, model.dof_limits.to(x.dtype))


def lbfgs(params: list[torch.Tensor], iterations: int, loss: Callable[[], torch.Tensor]) -> None:
    """Run ``iterations`` L-BFGS iterations (strong Wolfe line search) of ``loss`` on ``params``."""
    if iterations <= 0:
        return
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-12, tolerance_change=1e-15, history_size=20)

    def closure():
        opt.zero_grad()
        value = loss()
        value.backward()
        return value

    opt.step(closure)


class _PosedLandmarks:
    """The posed template's landmarks (B, L, 3); only the landmark triangles are skinned (LBS is
    per vertex)."""

    def __init__(self, model, selection: LandmarkSelection) -> None:
        self.model = model
        self.vidx = selection.vertices.reshape(-1)
        self.sub_t = model.template[self.vidx]  # (3L, 3)
        self.sub_w = model.weights[self.vidx]  # (3L, J)
        self.bary = selection.bary.to(model.template.dtype)
        self.n_lm = len(selection)

    def __call__(self, b, theta_or_x, go, tr, is_x=True, c=None) -> torch.Tensor:
        kw = {"pose": theta_or_x} if is_x else {"angles": theta_or_x}
        # Eq. 8: the shape offsets of the landmark vertices.
        tmpl = self.sub_t if c is None else self.sub_t + self.model.shape_decoder(c)[:, self.vidx]
        v = pose(self.model, tmpl, bone_scales=b, global_orient=go, transl=tr, weights=self.sub_w,
                 **kw).vertices
        return (v.reshape(-1, self.n_lm, 3, 3) * self.bary[..., None]).sum(2)  # (B, L, 3)


def _kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising ||R src + t - dst||^2 (both (N, 3))."""
    from scipy.spatial.transform import Rotation

    cs, cd = src.mean(0), dst.mean(0)
    if len(src) < 3:
        return np.zeros(3), cd - cs
    rot, _ = Rotation.align_vectors(dst - cd, src - cs)
    return rot.as_rotvec(), cd - rot.apply(cs)


def _initial_rigid(model, posed: _PosedLandmarks, selection: LandmarkSelection, x_lm: torch.Tensor,
                   mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Global orientation (B, 3) by Procrustes of the rest template's landmarks on the scan's (trunk
    landmarks when enough are located), then the translation (B, 3) that matches their means."""
    dtype = model.template.dtype
    bsz = mask.shape[0]
    rest = posed(model.bone_mean[None], torch.zeros(1, model.num_dofs, dtype=dtype), None, None, False)[0]
    bone_of = model.vertex_bones[selection.vertices[:, 0]]
    trunk = torch.tensor([model.bone_names[int(j)] in TRUNK_BONES for j in bone_of])
    go0 = torch.zeros(bsz, 3, dtype=dtype)
    for n in range(bsz):
        use = mask[n] & trunk if int((mask[n] & trunk).sum()) >= 4 else mask[n]
        rv, _ = _kabsch(rest[use].double().numpy(), x_lm[n, use].double().numpy())
        go0[n] = torch.as_tensor(rv, dtype=dtype)
    theta0 = torch.zeros(bsz, model.num_dofs, dtype=dtype)
    with torch.no_grad():
        p0 = posed(model.bone_mean.expand(bsz, -1), theta0, go0, None, False)
        w = mask[..., None].to(dtype)
        tr0 = ((x_lm - p0) * w).sum(1) / w.sum(1)
    return go0, tr0


def fit_landmarks(
    model,
    landmarks: torch.Tensor,
    selection: LandmarkSelection,
    config: RegisterConfig | None = None,
) -> Stage1:
    """Eq. 5.13: fit angles, bone scales and the global rigid motion to landmarks.

    Args:
        model: a :class:`blsm.BLSM` (float32 or float64).
        landmarks: (B, L, 3) target landmark positions in metres, in ``selection`` order; a row of
            NaN means the landmark was not located and is ignored.
        selection: the template landmarks A_lm.
        config: settings (defaults if None).

    Returns:
        :class:`Stage1` (detached).
    """
    cfg = config or RegisterConfig()
    dtype = model.template.dtype
    if landmarks.dim() != 3 or landmarks.shape[1:] != (len(selection), 3):
        raise ValueError(f"landmarks must be (B, {len(selection)}, 3), got {tuple(landmarks.shape)}")
    x_lm = landmarks.to(dtype)
    mask = torch.isfinite(x_lm).all(-1)  # (B, L)
    if (mask.sum(1) < 3).any():
        raise ValueError("every scan needs at least 3 located landmarks")
    x_lm = torch.where(mask[..., None], x_lm, torch.zeros_like(x_lm))
    bsz = mask.shape[0]
    posed = _PosedLandmarks(model, selection)
    use_shape = cfg.shape_init and model.num_shape_coeffs > 0
    beta = torch.zeros(bsz, model.num_shape_coeffs, dtype=dtype, requires_grad=use_shape)
    go0, tr0 = _initial_rigid(model, posed, selection, x_lm, mask)

    # An angle on a limit would start where tanh is flat (not the case for the packaged model).
    theta0 = torch.zeros(bsz, model.num_dofs, dtype=dtype)
    x = unconstrained_from_angles(theta0, model.dof_limits, eps=0.1).clone().requires_grad_(True)
    log_b = model.bone_mean.log().expand(bsz, -1).clone().requires_grad_(True)
    go = go0.clone().requires_grad_(True)
    tr = tr0.clone().requires_grad_(True)
    counts = mask.sum(1).to(dtype)
    names = model.bone_names
    pairs = [(names.index(n), names.index(n[:-2] + "_r")) for n in names if n.endswith("_l")]
    li = torch.tensor([p[0] for p in pairs])
    ri = torch.tensor([p[1] for p in pairs])

    def loss_fn(with_priors: bool) -> torch.Tensor:
        b = log_b.exp()
        p = posed(b, x, go, tr, c=beta if use_shape else None)
        d2 = ((p - x_lm).square().sum(-1) * mask).sum(1) / counts  # (B,) Eq. 5.13, mean over located
        loss = d2.sum()
        if with_priors:
            theta = pose_angles(model, x)
            loss = loss + cfg.angle_prior * theta.square().mean(1).sum()
            loss = loss + cfg.scale_prior * (log_b - model.bone_mean.log()).square().mean(1).sum()
            if cfg.symmetry_prior > 0:
                loss = loss + cfg.symmetry_prior * (log_b[:, li] - log_b[:, ri]).square().mean(1).sum()
            if use_shape:
                loss = loss + cfg.shape_prior * beta.square().mean(1).sum()
        return loss

    lbfgs([go, tr], cfg.stage1_rigid_iterations, lambda: loss_fn(False))
    lbfgs([x, log_b, go, tr], cfg.stage1_iterations, lambda: loss_fn(True))
    if use_shape:
        # Engineering addition (not in the thesis): the initial model's shape space, fitted with
        # the skeleton, moves soft-tissue landmarks (belly, chest, back) that bone scales cannot.
        lbfgs([beta, x, log_b, go, tr], cfg.stage1_shape_iterations, lambda: loss_fn(True))
    with torch.no_grad():
        b = log_b.exp()
        p = posed(b, x, go, tr, c=beta if use_shape else None)
        rms = (((p - x_lm).square().sum(-1) * mask).sum(1) / counts).sqrt()
        offs = model.shape_decoder(beta) if use_shape else torch.zeros(bsz, *model.template.shape, dtype=dtype)
        return Stage1(b.detach(), pose_angles(model, x).detach(), go.detach(), tr.detach(), rms,
                      beta.detach(), offs.detach())
