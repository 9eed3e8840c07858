"""The pure math of learning BLSM from registrations (thesis Sec. 5.4.2-5.4.4, Eqs. 5.26-5.31).

Bone lengths and their PCA (Sec. 5.4.2), the exact least squares of the bone correctives and mean
template (Eq. 5.27), the shape PCA of the T-pose residuals (Eqs. 5.28, 5.8), the blend-weight
parametrisation (Eq. 5.31) and the left/right symmetrisation they share. :mod:`blsm.learn.training.train`
runs them in order.

Units: metres; vertex arrays (..., V, 3), Y up, +X the body's left.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from blsm import skeleton

SYMMETRY_MODES = ("symmetrize", "augment")
_FLIP = (-1.0, 1.0, 1.0)


def bone_mirror_index(bone_names: Sequence[str]) -> list[int]:
    """Index of each bone's left/right counterpart (itself for central bones)."""
    return [list(bone_names).index(skeleton.mirror_name(n)) for n in bone_names]


def template_bone_lengths(model) -> torch.Tensor:
    """Bone lengths of a model's bind skeleton (build_anny's definition).

    A bone's length is the RMS distance from its head to its children's heads; a leaf ends at its
    tip keypoint (:data:`blsm.skeleton.LEAF_TIPS`) on the template.

    Args:
        model: a :class:`blsm.BLSM`.

    Returns:
        (J,) lengths in metres.
    """
    heads, parents = model.heads, model.parents
    out = []
    for j, name in enumerate(model.bone_names):
        kids = [c for c, p in enumerate(parents) if p == j]
        if kids:
            d = heads[kids] - heads[j]
        else:
            k = model.keypoint_names.index(skeleton.LEAF_TIPS[name])
            tip = (model.template[model.keypoint_vertices[k]] * model.keypoint_weights[k, :, None]).sum(0)
            d = (tip - heads[j])[None]
        out.append(d.pow(2).sum(-1).mean().sqrt())
    return torch.stack(out)


@dataclass
class BonePCA:
    """Result of :func:`bone_pca`.

    Attributes:
        mean_lengths: (J,) mean bone lengths in metres.
        directions: (Kb, J) unit principal directions in length space.
        std: (Kb,) standard deviations along them, metres.
        explained: (min(N, J),) fraction of the length variance per component.
        coeffs: (N, Kb) coefficients of the input bodies, in standard deviations.
    """

    mean_lengths: torch.Tensor
    directions: torch.Tensor
    std: torch.Tensor
    explained: torch.Tensor
    coeffs: torch.Tensor

    def basis(self, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(b_mean (J,), P_b (Kb, J)): mean and basis divided by ``reference`` lengths (Eq. 5.4)."""
        return self.mean_lengths / reference, self.directions * self.std[:, None] / reference

    def project(self, lengths: torch.Tensor) -> torch.Tensor:
        """(N, J) lengths -> (N, Kb) coefficients in standard deviations."""
        return (lengths - self.mean_lengths) @ self.directions.T / self.std


def bone_pca(lengths: torch.Tensor, num_coeffs: int, mirror: Sequence[int] | None = None) -> BonePCA:
    """PCA of bone lengths (Sec. 5.4.2), each body first averaged with its mirror image.

    Args:
        lengths: (N, J) bone lengths in metres, N >= 2.
        num_coeffs: number of components kept, <= J.
        mirror: (J,) bone mirror index; None skips the symmetrisation.

    Returns:
        :class:`BonePCA`.
    """
    if lengths.dim() != 2 or lengths.shape[0] < 2:
        raise ValueError(f"bone lengths must be (N >= 2, J), got {tuple(lengths.shape)}")
    x = lengths.double()
    if mirror is not None:
        x = 0.5 * (x + x[:, list(mirror)])
    mean = x.mean(0)
    _, sv, vt = torch.linalg.svd(x - mean, full_matrices=False)
    var = sv**2 / (x.shape[0] - 1)
    explained = var / var.sum().clamp(min=1e-30)
    k = min(num_coeffs, vt.shape[0])
    if k < num_coeffs:
        raise ValueError(f"bone PCA needs at least {num_coeffs} bodies for {num_coeffs} components, got {x.shape[0]}")
    # Components with (numerically) zero variance keep a tiny std so the coefficients stay finite.
    std = var[:k].sqrt().clamp(min=1e-9 * float(mean.abs().max()))
    directions = vt[:k]
    if mirror is not None:
        directions = 0.5 * (directions + directions[:, list(mirror)])
        directions = directions / directions.norm(dim=1, keepdim=True).clamp(min=1e-30)
    pca = BonePCA(mean, directions, std, explained, torch.zeros(0))
    pca.coeffs = pca.project(x)
    return pca


def _mirror_vertices(v: torch.Tensor, mirror: torch.Tensor) -> torch.Tensor:
    """(..., V, 3) -> mirror image across x = 0 in the same vertex order."""
    return v[..., mirror, :] * v.new_tensor(_FLIP)


def symmetrize_vertices(v: torch.Tensor, mirror: torch.Tensor) -> torch.Tensor:
    """Average (..., V, 3) positions or offsets with their mirror image (exactly symmetric)."""
    return 0.5 * (v + _mirror_vertices(v, mirror))


def blend_weights(raw: torch.Tensor, mask: torch.Tensor, eps: float) -> torch.Tensor:
    """Eq. 5.31: ``W = f(W') / sum_j f(W')_ij`` with ``f(x) = sqrt(x^2 + eps)``, on a support.

    Args:
        raw: (V, J) free parameters W'.
        mask: (V, J) bool support; at least one True per row.
        eps: epsilon of f.

    Returns:
        (V, J) weights, >= 0, zero off the support, rows summing to 1.
    """
    f = torch.sqrt(raw * raw + eps) * mask
    return f / f.sum(1, keepdim=True)


def weight_support(weights: torch.Tensor, parents: Sequence[int]) -> torch.Tensor:
    """(V, J) bool: each vertex's bones with non-zero weight plus their parents and children."""
    nz = weights > 0
    adj = torch.eye(len(parents), dtype=torch.bool, device=weights.device)
    for j, p in enumerate(parents):
        if p >= 0:
            adj[j, p] = adj[p, j] = True
    return (nz.float() @ adj.float()) > 0


def blended_transforms(weights: torch.Tensor, transforms: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-vertex blended transforms of Eq. 5.12: (B, V, 3, 3) M and (B, V, 3) t."""
    blend = torch.einsum("vj,njab->nvab", weights, transforms)
    return blend[..., :3], blend[..., 3]


def solve_correctives(
    targets: torch.Tensor,
    coeffs: torch.Tensor,
    linear: torch.Tensor,
    offset: torch.Tensor,
    ridge: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact minimiser of Eq. 5.27 for fixed per-vertex blended transforms.

    Minimises ``sum_n sum_i ||M_ni (v_i + sum_k c_nk p_ki) + t_ni - s_ni||^2 + ridge * sum ||p||^2``
    over v (V, 3) and p (Kb, V, 3), vertex by vertex.

    Args:
        targets: (N, V, 3) registrations S^ (posed), metres.
        coeffs: (N, Kb) bone coefficients c_b.
        linear: (N, V, 3, 3) blended linear parts M_ni.
        offset: (N, V, 3) blended translations t_ni.
        ridge: penalty on the correctives (absolute, not per registration).

    Returns:
        (template (V, 3), correctives (Kb, V, 3)) in float64.
    """
    normal, rhs = normal_equations(targets, coeffs, linear, offset)
    return solve_normal_equations(normal, rhs, ridge)


def normal_equations(targets, coeffs, linear, offset) -> tuple[torch.Tensor, torch.Tensor]:
    """The normal equations of :func:`solve_correctives`, to be summed over batches of registrations.

    Returns:
        (normal (K1, K1, V, 3, 3), rhs (K1, V, 3)) in float64, K1 = Kb + 1.
    """
    f64 = torch.float64
    n, v = targets.shape[:2]
    a = torch.cat([torch.ones(n, 1, dtype=f64, device=coeffs.device), coeffs.to(f64)], 1)  # (N, K1)
    m = linear.to(f64)
    g = m.transpose(-1, -2) @ m  # (N, V, 3, 3)
    r = (m.transpose(-1, -2) @ (targets.to(f64) - offset.to(f64))[..., None])[..., 0]  # (N, V, 3)
    k1 = a.shape[1]
    aa = (a[:, :, None] * a[:, None]).reshape(n, k1 * k1)
    normal = (aa.T @ g.reshape(n, v * 9)).reshape(k1, k1, v, 3, 3)
    rhs = (a.T @ r.reshape(n, v * 3)).reshape(k1, v, 3)
    return normal, rhs


def solve_normal_equations(
    normal: torch.Tensor, rhs: torch.Tensor, ridge: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Solve summed :func:`normal_equations` per vertex: (template (V, 3), correctives (Kb, V, 3))."""
    k1, _, v = normal.shape[:3]
    mat = normal.permute(2, 0, 3, 1, 4).reshape(v, 3 * k1, 3 * k1)  # (V, K1*3, K1*3)
    diag = torch.full((3 * k1,), float(ridge), dtype=mat.dtype, device=mat.device)
    diag[:3] = 1e-12  # the mean is always determined (M_ni is invertible)
    mat = mat + torch.diag(diag)
    sol = torch.linalg.solve(mat, rhs.permute(1, 0, 2).reshape(v, 3 * k1, 1))[..., 0]
    sol = sol.reshape(v, k1, 3)
    return sol[:, 0], sol[:, 1:].permute(1, 0, 2).contiguous()


def shape_pca(
    residuals: torch.Tensor, num_coeffs: int, mirror: torch.Tensor, symmetry: str = "symmetrize"
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Shape PCA of T-pose residuals (Eqs. 5.28, 5.8).

    Args:
        residuals: (N, V, 3) V_D in metres.
        num_coeffs: components kept (at most the number of samples - 1).
        mirror: (V,) vertex mirror map.
        symmetry: ``symmetrize`` (average each sample with its mirror) or ``augment`` (add mirrors).

    Returns:
        mean (V, 3), basis (Ks, V, 3) metres per standard deviation, coefficients (N, Ks) of the
        input samples in standard deviations, explained (Ks,) variance fractions.
    """
    n, v = residuals.shape[:2]
    x = residuals.double()
    if symmetry == "symmetrize":
        data = symmetrize_vertices(x, mirror)
    elif symmetry == "augment":
        data = torch.cat([x, _mirror_vertices(x, mirror)])
    else:
        raise ValueError(f"symmetry must be one of {SYMMETRY_MODES}, got {symmetry!r}")
    mean = data.mean(0)
    flat = (data - mean).reshape(len(data), -1)
    k = min(num_coeffs, len(data) - 1)
    if k < 1:
        raise ValueError(f"shape PCA needs at least 2 samples, got {n}")
    total = flat.pow(2).sum() / (len(data) - 1)
    if len(data) <= 4 * (k + 10):
        _, sv, vt = torch.linalg.svd(flat, full_matrices=False)
    else:
        _, sv, vh = torch.svd_lowrank(flat, q=k + 10, niter=4)
        vt = vh.T
    var = sv[:k] ** 2 / (len(data) - 1)
    std = var.sqrt().clamp(min=1e-12)
    directions = vt[:k]  # (Ks, 3V)
    if symmetry == "symmetrize":  # exact symmetry despite round-off
        d3 = directions.reshape(k, v, 3)
        directions = symmetrize_vertices(d3, mirror).reshape(k, -1)
    basis = (directions * std[:, None]).reshape(k, v, 3)
    coeffs = (x - mean).reshape(n, -1) @ directions.T / std
    return mean, basis, coeffs, var / total.clamp(min=1e-30)
