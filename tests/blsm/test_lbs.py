from __future__ import annotations

import torch

from blsm.lbs import blend_shapes, linear_blend_skinning, linear_shape


def _inputs(gen, b=2, v=30, j=5):
    verts = torch.randn(b, v, 3, generator=gen, dtype=torch.float64)
    w = torch.rand(v, j, generator=gen, dtype=torch.float64)
    w = w / w.sum(1, keepdim=True)
    lin = torch.randn(b, j, 3, 3, generator=gen, dtype=torch.float64)
    off = torch.randn(b, j, 3, generator=gen, dtype=torch.float64)
    return verts, w, lin, off


def test_lbs_matches_a_per_vertex_loop(gen):
    verts, w, lin, off = _inputs(gen)
    out = linear_blend_skinning(verts, w, lin, off)
    ref = torch.zeros_like(verts)
    for b in range(verts.shape[0]):
        for k in range(verts.shape[1]):
            acc = torch.zeros(3, dtype=torch.float64)
            for j in range(w.shape[1]):
                acc += w[k, j] * (lin[b, j] @ verts[b, k] + off[b, j])  # Eq. 12
            ref[b, k] = acc
    assert torch.allclose(out, ref, atol=1e-12)


def test_lbs_identity_transforms_return_input_exactly(gen):
    verts, w, _, _ = _inputs(gen)
    eye = torch.eye(3, dtype=torch.float64).expand(2, 5, 3, 3)
    out = linear_blend_skinning(verts, w, eye, torch.zeros(2, 5, 3, dtype=torch.float64))
    assert torch.equal(out, verts)


def test_lbs_gradcheck(gen):
    verts, w, lin, off = _inputs(gen, v=6, j=3)
    args = tuple(t.requires_grad_() for t in (verts, lin, off))
    assert torch.autograd.gradcheck(lambda v, l, o: linear_blend_skinning(v, w, l, o), args)


def test_blend_shapes_eqs_1_7_8(gen):
    tmpl = torch.randn(10, 3, generator=gen, dtype=torch.float64)
    cb = torch.randn(4, 2, generator=gen, dtype=torch.float64)
    pbc = torch.randn(2, 10, 3, generator=gen, dtype=torch.float64)
    cs = torch.randn(4, 3, generator=gen, dtype=torch.float64)
    ps = torch.randn(3, 10, 3, generator=gen, dtype=torch.float64)
    out = blend_shapes(tmpl, cb, pbc, linear_shape(cs, ps))
    ref = tmpl + (cb @ pbc.reshape(2, -1)).reshape(4, 10, 3) + (cs @ ps.reshape(3, -1)).reshape(4, 10, 3)
    assert torch.allclose(out, ref)
    assert torch.equal(blend_shapes(tmpl)[0], tmpl)
