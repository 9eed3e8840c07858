"""The PCA baseline of the mesh autoencoder: the Gram-matrix route equals the SVD's principal
subspace, and truncating a fit equals fitting fewer components."""

from __future__ import annotations

import pytest
import torch


@pytest.mark.parametrize("n", [12, 40])  # fewer meshes than coordinates (Gram route), and more
def test_pca_fit_matches_the_svd_subspace(n):
    from recovery.models.pca import PCAModel

    g = torch.Generator().manual_seed(0)
    v = 10  # 30 coordinates
    scales = torch.tensor([5.0, 3.0, 2.0, 1.0, 0.5, 0.2]).double()
    x = (torch.randn(n, 6, generator=g, dtype=torch.float64) * scales) @ torch.randn(6, 3 * v, generator=g, dtype=torch.float64)
    x = x + 0.01 * torch.randn(n, 3 * v, generator=g, dtype=torch.float64)
    meshes = x.float().reshape(n, v, 3)
    pca = PCAModel.fit(meshes, 4)
    c = pca.components.double()
    torch.testing.assert_close(c @ c.T, torch.eye(4, dtype=torch.float64), atol=1e-5, rtol=0)  # orthonormal rows
    xc = x - x.mean(0)
    vt = torch.linalg.svd(xc, full_matrices=False)[2][:4]
    torch.testing.assert_close(c.T @ c, vt.T @ vt, atol=1e-5, rtol=0)  # the same subspace (projector)
    # directions in order of variance
    var = (xc @ c.T).var(0)
    assert bool((var[:-1] >= var[1:]).all())
    two = PCAModel.fit(meshes, 2)
    torch.testing.assert_close(pca.truncated(2).reconstruct(meshes), two.reconstruct(meshes), atol=1e-4, rtol=0)


def test_pca_needs_as_many_meshes_as_components():
    from recovery.models.pca import PCAModel

    with pytest.raises(ValueError, match="at least 8 meshes"):
        PCAModel.fit(torch.zeros(5, 10, 3), 8)
