from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from recovery.eval.metrics import (
    confusion_matrix,
    foreground_scores,
    mpjpe,
    pa_mpjpe,
    pck,
    pelvis_aligned,
    pve,
    segmentation_scores,
    similarity_procrustes,
    similarity_transform,
)


def _rotations(gen, b, dtype=torch.float64):
    q, r = torch.linalg.qr(torch.randn(b, 3, 3, generator=gen, dtype=dtype))
    q = q * torch.sign(torch.diagonal(r, dim1=1, dim2=2))[:, None]
    return q * torch.sign(torch.linalg.det(q))[:, None, None]  # det +1


def _naive_similarity(s1: np.ndarray, s2: np.ndarray) -> np.ndarray:
    """HMR / SPIN's compute_similarity_transform for one (N, 3) sample, as they wrote it."""
    s1, s2 = s1.T, s2.T
    mu1, mu2 = s1.mean(1, keepdims=True), s2.mean(1, keepdims=True)
    x1, x2 = s1 - mu1, s2 - mu2
    var1 = np.sum(x1**2)
    k = x1 @ x2.T
    u, _, vh = np.linalg.svd(k)
    v = vh.T
    z = np.eye(3)
    z[-1, -1] *= np.sign(np.linalg.det(u @ v.T))
    r = v @ z @ u.T
    scale = np.trace(r @ k) / var1
    t = mu2 - scale * (r @ mu1)
    return (scale * r @ s1 + t).T


def test_pa_mpjpe_of_a_similar_copy_is_zero_and_the_transform_is_recovered(gen):
    target = torch.randn(4, 20, 3, generator=gen, dtype=torch.float64)
    rot = _rotations(gen, 4)
    scale = torch.tensor([0.5, 1.0, 2.0, 3.7], dtype=torch.float64)
    shift = torch.randn(4, 3, generator=gen, dtype=torch.float64)
    pred = scale[:, None, None] * target @ rot.transpose(1, 2) + shift[:, None]
    assert mpjpe(pred, target).min() > 0.1  # the copy really is moved
    assert pa_mpjpe(pred, target).max() < 1e-5
    s, r, t = similarity_transform(pred, target)
    assert torch.allclose(s, 1 / scale, atol=1e-10)
    assert torch.allclose(r, rot.transpose(1, 2), atol=1e-10)
    assert torch.allclose(similarity_procrustes(pred, target), target, atol=1e-10)
    # pred = 2 * target + t: scale and shift only.
    assert pa_mpjpe(2 * target + torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64), target).max() < 1e-10


def test_a_mirror_image_is_not_aligned_by_a_reflection(gen):
    target = torch.randn(3, 15, 3, generator=gen, dtype=torch.float64)
    pred = target * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)  # reflection x -> -x
    s, r, t = similarity_transform(pred, target)
    assert torch.allclose(torch.linalg.det(r), torch.ones(3, dtype=torch.float64), atol=1e-10)
    err = pa_mpjpe(pred, target)
    assert (err > 0.05).all()  # an orthogonal Procrustes allowing det -1 would give 0 here

    def cost(rot):
        return ((s[:, None, None] * pred @ rot.transpose(1, 2) + t[:, None] - target) ** 2).sum((1, 2))

    # The returned rotation is a minimum over proper rotations: small rotations only make it worse.
    best = cost(r)
    for _ in range(20):
        w = 1e-3 * torch.randn(3, 3, generator=gen, dtype=torch.float64)
        small = torch.linalg.matrix_exp(w - w.T)[None]
        assert (cost(small @ r) >= best - 1e-12).all()


def test_hand_computed_mpjpe():
    target = torch.zeros(1, 2, 3, dtype=torch.float64)
    pred = torch.tensor([[[3.0, 4.0, 0.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    assert mpjpe(pred, target).tolist() == [3.0]  # (5 + 1) / 2
    assert mpjpe(pred, target, torch.tensor([[1.0, 3.0]])).tolist() == [2.0]  # (5 + 3) / 4
    assert mpjpe(pred, target, torch.tensor([[0.0, 1.0]])).tolist() == [1.0]


@pytest.mark.parametrize("delta", [0.1, 0.5])
def test_pa_mpjpe_of_a_symmetric_perturbation_matches_the_closed_form(delta):
    # Target: the 6 octahedron points +-e_i, each twice (N = 12). Pred: q_n + d_n with d_n a tangent
    # offset of length delta, +t for one copy and -t for the other (t a unit vector _|_ q_n).
    # Proof of the optimum: sum q_n = sum d_n = 0, so both centroids are 0. The cross covariance
    # (1/N) sum q_n p_n^T = (1/N) (sum q q^T + sum q d^T) = (4 I + 0) / 12 = I / 3, so the best
    # rotation maximises trace(R) / 3: R = I, uniquely. Scale s = trace(R Sigma) / var_p with
    # var_p = (1/N) sum |q_n + d_n|^2 = 1 + delta^2 (q _|_ d), so s = 1 / (1 + delta^2) and t = 0.
    # Residual s p_n - q_n = (s - 1) q_n + s d_n has |.|^2 = (s - 1)^2 + s^2 delta^2
    # = delta^2 / (1 + delta^2), the same for every point: PA-MPJPE = delta / sqrt(1 + delta^2).
    eye = np.eye(3)
    q, d = [], []
    for i in range(3):
        for sign in (1.0, -1.0):
            for tsign in (1.0, -1.0):
                q.append(sign * eye[i])
                d.append(tsign * delta * eye[(i + 1) % 3])
    target = torch.tensor(np.array(q))[None]
    pred = target + torch.tensor(np.array(d))[None]
    assert mpjpe(pred, target).item() == pytest.approx(delta, abs=1e-12)
    s, r, t = similarity_transform(pred, target)
    assert s.item() == pytest.approx(1 / (1 + delta**2), abs=1e-12)
    assert torch.allclose(r[0], torch.eye(3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(t, torch.zeros(1, 3, dtype=torch.float64), atol=1e-12)
    assert pa_mpjpe(pred, target).item() == pytest.approx(delta / math.sqrt(1 + delta**2), abs=1e-12)


def test_batched_procrustes_matches_a_per_sample_numpy_svd(gen):
    target = torch.randn(6, 17, 3, generator=gen, dtype=torch.float64)
    noise = 0.3 * torch.randn(6, 17, 3, generator=gen, dtype=torch.float64)
    pred = 0.8 * target @ _rotations(gen, 6).transpose(1, 2) + noise
    pred[::2, :, 0] *= -1  # half the batch needs the reflection fix
    out = similarity_procrustes(pred, target)
    for b in range(6):
        ref = _naive_similarity(pred[b].numpy(), target[b].numpy())
        np.testing.assert_allclose(out[b].numpy(), ref, atol=1e-10)
    out32 = similarity_procrustes(pred.float(), target.float())
    assert out32.dtype == torch.float32
    assert torch.allclose(out32.double(), out, atol=1e-4)


def test_zero_weights_ignore_points_entirely(gen):
    target = torch.randn(3, 10, 3, generator=gen, dtype=torch.float64)
    noise = 0.2 * torch.randn(3, 10, 3, generator=gen, dtype=torch.float64)
    pred = target @ _rotations(gen, 3).transpose(1, 2) + noise
    w = torch.ones(3, 10, dtype=torch.float64)
    w[:, 6:] = 0
    pred_junk = pred.clone()
    pred_junk[:, 6:] = 100.0  # outliers the weights must hide
    assert torch.allclose(pa_mpjpe(pred_junk, target, w), pa_mpjpe(pred[:, :6], target[:, :6]), atol=1e-10)
    assert torch.allclose(mpjpe(pred_junk, target, w), mpjpe(pred[:, :6], target[:, :6]), atol=1e-12)


def test_pa_mpjpe_runs_under_autograd(gen):
    target = torch.randn(2, 8, 3, generator=gen, dtype=torch.float64)
    pred = (target + 0.1 * torch.randn(2, 8, 3, generator=gen, dtype=torch.float64)).requires_grad_()
    pa_mpjpe(pred, target).sum().backward()
    assert torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0


def test_procrustes_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"\(B, N, 3\)"):
        pa_mpjpe(torch.zeros(4, 3), torch.zeros(4, 3))
    with pytest.raises(ValueError, match="same shape"):
        mpjpe(torch.zeros(1, 4, 3), torch.zeros(1, 5, 3))
    with pytest.raises(ValueError, match="weights"):
        mpjpe(torch.zeros(1, 4, 3), torch.zeros(1, 4, 3), torch.ones(4))


def test_pelvis_alignment_and_pve():
    target = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]], dtype=torch.float64)
    shift = torch.tensor([0.5, -2.0, 3.0], dtype=torch.float64)
    pred = target + shift
    pred[0, 2, 2] += 0.3  # one vertex off by 0.3 along z
    assert torch.equal(pelvis_aligned(target + shift, 0), target)
    expected = target.clone()
    expected[0, 2, 2] = 0.3
    assert torch.allclose(pelvis_aligned(pred, shift[None]), expected)
    assert pve(pred, target, 0).item() == pytest.approx(0.1)  # (0 + 0 + 0.3) / 3
    assert pve(pred, target, shift[None], torch.zeros(1, 3, dtype=torch.float64)).item() == pytest.approx(0.1)
    assert mpjpe(pred, target).item() > 2  # unaligned, the shift dominates
    with pytest.raises(ValueError, match="target_root"):
        pve(pred, target, shift[None])
    with pytest.raises(ValueError, match="outside"):
        pelvis_aligned(pred, 3)


def test_pck_hand_example():
    target = torch.zeros(2, 4, 2)
    pred = torch.tensor([[[0.0, 0.0], [3.0, 0.0], [3.0, 4.0], [10.0, 0.0]], [[1.0, 0.0]] * 4])
    visible = torch.tensor([[True, True, True, False], [False] * 4])
    out = pck(pred, target, visible, 5.0)
    # Sample 0: distances 0, 3, 5 visible; 5 is not strictly below 5 -> 2 / 3. Sample 1: none visible.
    assert out[0].item() == pytest.approx(2 / 3)
    assert torch.isnan(out[1])
    per_sample = pck(pred, target, torch.tensor([[True] * 4, [True] * 4]), torch.tensor([5.1, 0.5]))
    assert per_sample.tolist() == [0.75, 0.0]
    with pytest.raises(ValueError, match="bool"):
        pck(pred, target, visible.float(), 5.0)
    with pytest.raises(ValueError, match="positive"):
        pck(pred, target, visible, 0.0)


def test_confusion_matrix_and_scores_hand_example():
    target = torch.tensor([0, 0, 1, 1, 2, 2])
    pred = torch.tensor([0, 1, 1, 1, 2, 0])
    conf = confusion_matrix(pred, target, 4)  # class 3 occurs nowhere
    assert conf.dtype == torch.int64
    assert conf.tolist() == [[1, 1, 0, 0], [0, 2, 0, 0], [1, 0, 1, 0], [0, 0, 0, 0]]
    scores = segmentation_scores(conf)
    assert scores["accuracy"] == pytest.approx(4 / 6)
    # F1 = 2TP / (2TP + FP + FN): class 0: 2/4, class 1: 4/5, class 2: 2/3; class 3 undefined, left out.
    f1 = scores["f1"]
    assert f1[:3].tolist() == pytest.approx([0.5, 0.8, 2 / 3])
    assert torch.isnan(f1[3])
    assert scores["macro_f1"] == pytest.approx((0.5 + 0.8 + 2 / 3) / 3)
    fg = foreground_scores(conf, background=0)
    # fg = {1, 2, 3}: TP 3, FN 1 (2 -> 0), FP 1 (0 -> 1), TN 1.
    assert fg["accuracy"] == pytest.approx(4 / 6)
    assert fg["f1"] == pytest.approx(6 / 8)
    assert fg["precision"] == pytest.approx(0.75) and fg["recall"] == pytest.approx(0.75)


def test_confusion_matrix_matches_a_naive_loop_and_accumulates():
    rng = np.random.default_rng(0)
    target = rng.integers(0, 5, size=(3, 6, 7))
    pred = np.where(rng.random((3, 6, 7)) < 0.6, target, rng.integers(0, 5, size=(3, 6, 7)))
    ref = np.zeros((5, 5), np.int64)
    for t, p in zip(target.ravel(), pred.ravel(), strict=True):
        ref[t, p] += 1
    conf = confusion_matrix(pred, target, 5)
    assert conf.tolist() == ref.tolist()
    summed = sum(confusion_matrix(pred[i], target[i], 5) for i in range(3))
    assert torch.equal(summed, conf)
    f1 = [2 * ref[c, c] / (ref[c].sum() + ref[:, c].sum()) for c in range(5)]
    scores = segmentation_scores(conf)
    assert scores["accuracy"] == pytest.approx(np.trace(ref) / ref.sum())
    assert scores["macro_f1"] == pytest.approx(np.mean(f1))


def test_segmentation_inputs_are_checked():
    with pytest.raises(ValueError, match=r"\[0, 3\)"):
        confusion_matrix(torch.tensor([0, 3]), torch.tensor([0, 1]), 3)
    with pytest.raises(ValueError, match="integer"):
        confusion_matrix(torch.tensor([0.0]), torch.tensor([0]), 3)
    with pytest.raises(ValueError, match="square"):
        segmentation_scores(torch.zeros(2, 3))
    with pytest.raises(ValueError, match="background"):
        foreground_scores(torch.zeros(2, 2), background=2)
