"""The linear baseline of the mesh autoencoder (thesis Table 4.3): PCA on flattened body-frame meshes."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class PCAModel:
    """Linear baseline: ``V = mean + coeffs @ components`` on flattened meshes."""

    mean: torch.Tensor  # (V * 3,)
    components: torch.Tensor  # (k, V * 3), orthonormal rows

    @classmethod
    def fit(cls, meshes: torch.Tensor, k: int) -> PCAModel:
        """The top-``k`` principal directions of ``meshes`` (N, V, 3), in order of variance.

        With fewer meshes than coordinates (N < 3V) the right singular vectors come from the N x N
        Gram matrix: ``X X^T = U S^2 U^T``, ``V_k^T = S_k^-1 U_k^T X`` (float64; exact up to rounding
        for the kept directions, and about N/3V the cost of the full SVD).
        """
        x = meshes.reshape(len(meshes), -1).double()
        mean = x.mean(0)
        x = x - mean
        if k > min(x.shape):
            raise ValueError(f"PCA with {k} components needs at least {k} meshes, got {len(meshes)}")
        if x.shape[0] < x.shape[1]:
            evals, u = torch.linalg.eigh(x @ x.T)  # ascending
            evals, u = evals.flip(0)[:k], u.flip(1)[:, :k]
            vt = (u.T @ x) / evals.clamp_min(1e-300).sqrt()[:, None]
        else:
            vt = torch.linalg.svd(x, full_matrices=False)[2][:k]
        return cls(mean=mean.float(), components=vt.float())

    def truncated(self, k: int) -> PCAModel:
        """The same model with its first ``k`` components (PCA with ``k`` components of the same data)."""
        return PCAModel(mean=self.mean, components=self.components[:k])

    def reconstruct(self, meshes: torch.Tensor) -> torch.Tensor:
        x = meshes.reshape(len(meshes), -1) - self.mean
        return ((x @ self.components.T) @ self.components + self.mean).reshape(meshes.shape)
