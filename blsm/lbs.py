"""Template synthesis (Eqs. 1, 7, 8) and linear blend skinning (Eq. 12) as pure functions."""

from __future__ import annotations

import torch


def blend_shapes(
    template: torch.Tensor,
    bone_coeffs: torch.Tensor | None = None,
    bone_correctives: torch.Tensor | None = None,
    shape_offsets: torch.Tensor | None = None,
) -> torch.Tensor:
    """Eqs. 1 and 7: ``V = V_mean + c_b P_bc + V_s``.

    Args:
        template: (V, 3) mean template V_mean in metres.
        bone_coeffs: (B, Kb) bone coefficients c_b, or None.
        bone_correctives: (Kb, V, 3) bone-corrective blendshapes P_bc.
        shape_offsets: (B, V, 3) identity shape update V_s (Eq. 8 ``c_s P_s`` or the
            mesh-convolution decoder of Eq. 11), or None.

    Returns:
        (B, V, 3) person template; exactly ``template`` where every term is absent.
    """
    batch = 1
    for t in (bone_coeffs, shape_offsets):
        if t is not None:
            batch = t.shape[0]
    out = template.expand(batch, -1, -1)
    if bone_coeffs is not None and bone_correctives is not None:
        out = out + torch.einsum("bk,kvc->bvc", bone_coeffs, bone_correctives)
    if shape_offsets is not None:
        out = out + shape_offsets
    return out


def linear_shape(coeffs: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
    """Eq. 8: ``V_s = c_s P_s``.

    Args:
        coeffs: (B, Ks) shape coefficients c_s (in standard deviations).
        basis: (Ks, V, 3) shape components P_s in metres per standard deviation.

    Returns:
        (B, V, 3) shape offsets.
    """
    return torch.einsum("bk,kvc->bvc", coeffs, basis)


def linear_blend_skinning(
    vertices: torch.Tensor,
    weights: torch.Tensor,
    linear: torch.Tensor,
    offset: torch.Tensor,
) -> torch.Tensor:
    """Eq. 12: ``v^_k = sum_j w_kj A_j v_k`` with ``A_j = T_j T^_j^{-1}``.

    Evaluated as ``v + sum_j w_kj ((L_j - I) v + t_j)``, which equals Eq. 12 because each row of
    ``weights`` sums to 1, and returns the input exactly when every A_j is exactly the identity.

    Args:
        vertices: (B, V, 3) rest-pose vertices in metres.
        weights: (V, J) skinning weights, >= 0, rows summing to 1.
        linear: (B, J, 3, 3) linear parts L_j of the skinning transforms.
        offset: (B, J, 3) translations t_j of the skinning transforms.

    Returns:
        (B, V, 3) posed vertices.
    """
    eye = torch.eye(3, dtype=linear.dtype, device=linear.device)
    batch, num_joints = linear.shape[:2]
    # Blend [L - I | t] with one (V, J) x (J, 12) matmul per batch, then apply per vertex.
    packed = torch.cat([(linear - eye).reshape(batch, num_joints, 9), offset], dim=-1)  # (B, J, 12)
    blended = weights @ packed  # (B, V, 12)
    mat = blended[..., :9].reshape(batch, -1, 3, 3)
    moved = (mat @ vertices[..., None])[..., 0]  # (B, V, 3)
    return vertices + moved + blended[..., 9:]


def unskin(posed: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """The inverse of Eq. 12 per vertex: rest positions ``T`` with ``sum_j w_ij (L_j T_i + t_j)``
    equal to the posed positions (each vertex's blended transform ``A_i = sum_j w_ij [L_j | t_j]``
    solved, not the blend of the inverses).

    Args:
        posed: (..., V, 3) posed positions.
        weights: (V, J) skinning weights.
        transforms: (..., J, 3, 4) skinning transforms ``[L_j | t_j]``.

    Returns:
        (..., V, 3) rest positions.
    """
    blend = torch.einsum("vj,...jab->...vab", weights, transforms)  # (..., V, 3, 4)
    return torch.linalg.solve(blend[..., :3], (posed - blend[..., 3])[..., None])[..., 0]
