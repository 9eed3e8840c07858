"""Evaluation metrics for mesh recovery: 3D joint / vertex errors, 2D PCK and segmentation scores.

All functions are pure and batched. 3D errors are returned in the unit of their input (metres for
everything this project produces; multiply by 1000 for the millimetres papers report). They run
under autograd but are meant for evaluation: call them inside ``torch.no_grad()``.

Segmentation scores accumulate over a dataset by summing the (C, C) confusion matrices of its
images and scoring the sum once (micro-averaged over pixels, as thesis Table 6.4 reports them).
"""

from __future__ import annotations

import numpy as np
import torch


def _check_points(name: str, x: torch.Tensor, dim: int = 3) -> None:
    if not isinstance(x, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.ndim != 3 or x.shape[-1] != dim:
        raise ValueError(f"{name} must be (B, N, {dim}), got {tuple(x.shape)}")


def _check_pair(pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor | None, dim: int = 3) -> None:
    _check_points("pred", pred, dim)
    _check_points("target", target, dim)
    if pred.shape != target.shape:
        raise ValueError(
            f"pred and target must have the same shape, got {tuple(pred.shape)} and {tuple(target.shape)}"
        )
    if weights is not None and tuple(weights.shape) != tuple(pred.shape[:2]):
        raise ValueError(f"weights must be (B, N) = {tuple(pred.shape[:2])}, got {tuple(weights.shape)}")


def _weighted_mean(values: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:
    """(B, N) -> (B,): plain or weighted mean over N (NaN where the weights sum to 0)."""
    if weights is None:
        return values.mean(dim=1)
    weights = weights.to(values.dtype)
    return (values * weights).sum(dim=1) / weights.sum(dim=1)


def similarity_transform(
    pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The similarity transform that best maps ``pred`` onto ``target`` in the least-squares sense.

    Minimises ``sum_n w_n |s R p_n + t - q_n|^2`` over a scale ``s``, a proper rotation ``R``
    (det +1) and a translation ``t`` with Umeyama's closed form (1991): the SVD of the cross
    covariance, with the sign of the last singular direction flipped where the unconstrained
    optimum would be a reflection. The batched equivalent of HMR / SPIN's
    ``compute_similarity_transform``.

    Args:
        pred: (B, N, 3) points to move (any length unit).
        target: (B, N, 3) corresponding points to align to, same unit.
        weights: (B, N) non-negative point weights (e.g. keypoint visibility), or None for all 1.

    Returns:
        ``scale`` (B,), ``rotation`` (B, 3, 3) and ``translation`` (B, 3) such that
        ``scale * pred @ rotation.T + translation`` is the aligned ``pred``. Where ``pred`` has no
        spread (all points, or all weighted points, coincide) the scale is 0, so the aligned
        points all sit at the target's (weighted) centroid. A sample whose weights sum to 0 gives NaN.

    Raises:
        ValueError: on shapes that are not (B, N, 3) / (B, N) or that disagree.
    """
    _check_pair(pred, target, weights)
    if weights is None:
        weights = torch.ones(pred.shape[:2], dtype=pred.dtype, device=pred.device)
    w = weights.to(pred.dtype)[..., None]  # (B, N, 1)
    total = w.sum(dim=1)  # (B, 1)
    mu_p = (w * pred).sum(dim=1) / total  # (B, 3)
    mu_q = (w * target).sum(dim=1) / total  # (B, 3)
    p = pred - mu_p[:, None]  # (B, N, 3)
    q = target - mu_q[:, None]  # (B, N, 3)
    var_p = (w * p * p).sum(dim=(1, 2)) / total[:, 0]  # (B,)
    cov = torch.einsum("bn,bni,bnj->bij", w[..., 0], q, p) / total[..., None]  # (B, 3, 3) target x pred
    u, sigma, vh = torch.linalg.svd(cov)
    # Umeyama's S = diag(1, 1, -1) where det(U V^T) < 0: the best proper rotation instead of a mirror.
    sign = torch.where(torch.linalg.det(u) * torch.linalg.det(vh) < 0, -1.0, 1.0).to(pred.dtype)  # (B,)
    d = torch.ones_like(sigma)
    d = torch.cat([d[:, :2], sign[:, None]], dim=1)  # (B, 3)
    rotation = u @ (d[..., None] * vh)  # (B, 3, 3)
    trace = (sigma * d).sum(dim=1)
    scale = torch.where(var_p > 0, trace / torch.where(var_p > 0, var_p, 1.0), 0.0)
    translation = mu_q - scale[:, None] * (rotation @ mu_p[..., None])[..., 0]
    return scale, rotation, translation


def similarity_procrustes(
    pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor | None = None
) -> torch.Tensor:
    """``pred`` aligned to ``target`` by the best similarity transform (see :func:`similarity_transform`).

    Args:
        pred: (B, N, 3) points to move.
        target: (B, N, 3) corresponding points, same unit.
        weights: (B, N) non-negative point weights, or None.

    Returns:
        (B, N, 3) ``s R pred + t`` in the unit of the input.
    """
    scale, rotation, translation = similarity_transform(pred, target, weights)
    return scale[:, None, None] * pred @ rotation.transpose(1, 2) + translation[:, None]


def mpjpe(pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Mean per-joint position error: the mean Euclidean distance between corresponding points.

    No alignment is applied; see :func:`pelvis_aligned` and :func:`pa_mpjpe`.

    Args:
        pred: (B, N, 3) predicted points.
        target: (B, N, 3) ground-truth points, same unit.
        weights: (B, N) non-negative weights (e.g. 0/1 visibility) for a weighted mean, or None.

    Returns:
        (B,) per-sample error in the unit of the input (NaN where the weights sum to 0).
    """
    _check_pair(pred, target, weights)
    return _weighted_mean(torch.linalg.vector_norm(pred - target, dim=-1), weights)


def pa_mpjpe(pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Procrustes-aligned MPJPE: :func:`mpjpe` after :func:`similarity_procrustes`.

    The weights enter both the alignment and the mean, so points of weight 0 are ignored entirely.

    Args:
        pred: (B, N, 3) predicted points.
        target: (B, N, 3) ground-truth points, same unit.
        weights: (B, N) non-negative weights, or None.

    Returns:
        (B,) per-sample error in the unit of the input.
    """
    return mpjpe(similarity_procrustes(pred, target, weights), target, weights)


def pelvis_aligned(x: torch.Tensor, pelvis: int | torch.Tensor) -> torch.Tensor:
    """Points translated so that the pelvis (root) sits at the origin.

    Args:
        x: (B, N, 3) joints or vertices.
        pelvis: the index of the pelvis among the N points, or its (B, 3) positions (e.g. the
            pelvis joint regressed from vertices), in the unit of ``x``.

    Returns:
        (B, N, 3) ``x - pelvis``.

    Raises:
        ValueError: on a bad shape or an index outside [-N, N).
    """
    _check_points("x", x)
    if isinstance(pelvis, int):
        if not -x.shape[1] <= pelvis < x.shape[1]:
            raise ValueError(f"pelvis index {pelvis} is outside the {x.shape[1]} points of x")
        root = x[:, pelvis]
    else:
        if not isinstance(pelvis, torch.Tensor) or tuple(pelvis.shape) != (x.shape[0], 3):
            shape = tuple(pelvis.shape) if isinstance(pelvis, torch.Tensor) else type(pelvis).__name__
            raise ValueError(
                f"pelvis must be an int index or a (B, 3) = ({x.shape[0]}, 3) tensor, got {shape}"
            )
        root = pelvis
    return x - root[:, None]


def pve(
    pred_vertices: torch.Tensor,
    target_vertices: torch.Tensor,
    pred_root: int | torch.Tensor,
    target_root: int | torch.Tensor | None = None,
) -> torch.Tensor:
    """Per-vertex error after aligning prediction and ground truth at their root (pelvis).

    Each mesh is translated so that its own root is at the origin, then the mean Euclidean
    distance over vertices is taken: no rotation or scale is fitted. This is the pelvis-aligned
    PVE of SPIN and 4D-Humans (HMR 2.0), which subtract from each mesh its own pelvis joint
    regressed from that mesh.

    Args:
        pred_vertices: (B, V, 3) predicted vertices.
        target_vertices: (B, V, 3) ground-truth vertices (same topology), same unit.
        pred_root: the predicted root as a vertex index or as (B, 3) positions (e.g. the pelvis
            joint regressed from ``pred_vertices``).
        target_root: the ground-truth root likewise; None uses ``pred_root`` when it is an index.

    Returns:
        (B,) mean per-vertex error in the unit of the input.

    Raises:
        ValueError: on bad shapes, or when ``target_root`` is None and ``pred_root`` is not an index.
    """
    _check_pair(pred_vertices, target_vertices, None)
    if target_root is None:
        if not isinstance(pred_root, int):
            raise ValueError("target_root is required when pred_root is given as positions, not an index")
        target_root = pred_root
    return mpjpe(pelvis_aligned(pred_vertices, pred_root), pelvis_aligned(target_vertices, target_root))


def pck(
    pred_2d: torch.Tensor,
    target_2d: torch.Tensor,
    visible: torch.Tensor,
    threshold: float | torch.Tensor,
) -> torch.Tensor:
    """Percentage of correct keypoints: the fraction of visible keypoints within ``threshold``.

    A keypoint is correct when its Euclidean distance to the ground truth is strictly below the
    threshold (as MMPose and 4D-Humans count it).

    Args:
        pred_2d: (B, K, 2) predicted keypoints in pixels.
        target_2d: (B, K, 2) ground-truth keypoints in pixels.
        visible: (B, K) bool, the keypoints to score.
        threshold: distance in pixels, a float or a (B,) tensor (e.g. 0.05 * each crop's size).

    Returns:
        (B,) fraction in [0, 1] as ``pred_2d``'s dtype; NaN for a sample with no visible keypoint.

    Raises:
        ValueError: on bad shapes, a non-bool ``visible`` or a non-positive threshold.
    """
    _check_pair(pred_2d, target_2d, None, dim=2)
    if not isinstance(visible, torch.Tensor) or visible.dtype != torch.bool:
        raise ValueError("visible must be a bool tensor (B, K)")
    if tuple(visible.shape) != tuple(pred_2d.shape[:2]):
        raise ValueError(f"visible must be (B, K) = {tuple(pred_2d.shape[:2])}, got {tuple(visible.shape)}")
    thr = torch.as_tensor(threshold, dtype=pred_2d.dtype, device=pred_2d.device)
    if thr.ndim == 0:
        thr = thr.expand(pred_2d.shape[0])
    if tuple(thr.shape) != (pred_2d.shape[0],):
        raise ValueError(
            f"threshold must be a float or a (B,) = ({pred_2d.shape[0]},) tensor, got {tuple(thr.shape)}"
        )
    if not bool((thr > 0).all()):
        raise ValueError(f"threshold must be positive pixels, got {thr.tolist()}")
    correct = torch.linalg.vector_norm(pred_2d - target_2d, dim=-1) < thr[:, None]  # (B, K)
    hits = (correct & visible).sum(dim=1).to(pred_2d.dtype)
    count = visible.sum(dim=1).to(pred_2d.dtype)
    return hits / count  # 0 / 0 = NaN where nothing is visible


def confusion_matrix(
    pred: torch.Tensor | np.ndarray, target: torch.Tensor | np.ndarray, num_classes: int
) -> torch.Tensor:
    """Pixel counts by (true class, predicted class).

    Args:
        pred: (...) integer predicted labels in [0, num_classes), any shape (e.g. (B, H, W)).
        target: (...) integer true labels, same shape.
        num_classes: C.

    Returns:
        (C, C) int64 tensor (on CPU for numpy input); entry ``[t, p]`` counts pixels of true class
        ``t`` predicted as ``p`` (rows target, columns prediction). Sum these over a dataset.

    Raises:
        ValueError: on non-integer labels, mismatched shapes or a label outside [0, C).
    """
    pred_t, target_t = torch.as_tensor(pred), torch.as_tensor(target)
    if isinstance(num_classes, bool) or not isinstance(num_classes, int) or num_classes < 1:
        raise ValueError(f"num_classes must be a positive int, got {num_classes!r}")
    for name, t in (("pred", pred_t), ("target", target_t)):
        if t.dtype.is_floating_point or t.dtype.is_complex or t.dtype == torch.bool:
            raise ValueError(f"{name} must hold integer class labels, got {t.dtype}")
    if pred_t.shape != target_t.shape:
        raise ValueError(
            f"pred and target must have the same shape, got {tuple(pred_t.shape)} and {tuple(target_t.shape)}"
        )
    pred_t, target_t = pred_t.reshape(-1).long(), target_t.to(pred_t.device).reshape(-1).long()
    for name, t in (("pred", pred_t), ("target", target_t)):
        if t.numel() and (int(t.min()) < 0 or int(t.max()) >= num_classes):
            raise ValueError(
                f"{name} labels must be in [0, {num_classes}), got [{int(t.min())}, {int(t.max())}]"
            )
    counts = torch.bincount(target_t * num_classes + pred_t, minlength=num_classes * num_classes)
    return counts.reshape(num_classes, num_classes)


def _check_confusion(conf: torch.Tensor | np.ndarray) -> torch.Tensor:
    conf_t = torch.as_tensor(conf)
    if conf_t.ndim != 2 or conf_t.shape[0] != conf_t.shape[1] or conf_t.shape[0] < 1:
        raise ValueError(f"conf must be a square (C, C) confusion matrix, got {tuple(conf_t.shape)}")
    if bool((conf_t < 0).any()):
        raise ValueError("conf must hold non-negative counts")
    return conf_t.to(torch.float64)


def segmentation_scores(conf: torch.Tensor | np.ndarray) -> dict[str, float | torch.Tensor]:
    """Pixel accuracy and F1 scores from a confusion matrix (rows target, columns prediction).

    The F1 of class c is ``2 TP / (2 TP + FP + FN)``. The macro F1 averages it over the classes
    that occur in the target or in the prediction; a class absent from both has no defined F1
    (0 / 0) and is left out rather than counted as 0 or 1, so a crop without, say, a visible left
    foot is not rewarded or punished for it. For thesis Table 6.4's "6 parts + background" score,
    pass the 7-class matrix summed over the test set.

    Args:
        conf: (C, C) counts from :func:`confusion_matrix`, possibly summed over many images.

    Returns:
        ``{"accuracy": float, "macro_f1": float, "f1": (C,) float64 tensor}``: overall pixel
        accuracy (trace / total), the macro F1 and the per-class F1 (NaN for absent classes).
        Accuracy is NaN for an empty matrix, the macro F1 NaN when no class occurs.

    Raises:
        ValueError: on a non-square or negative matrix.
    """
    c = _check_confusion(conf)
    tp = torch.diagonal(c)
    support = c.sum(dim=1) + c.sum(dim=0)  # 2 TP + FN + FP
    f1 = torch.where(support > 0, 2 * tp / torch.where(support > 0, support, 1.0), torch.nan)
    present = support > 0
    macro = float(f1[present].mean()) if bool(present.any()) else float("nan")
    total = float(c.sum())
    accuracy = float(tp.sum()) / total if total > 0 else float("nan")
    return {"accuracy": accuracy, "macro_f1": macro, "f1": f1}


def foreground_scores(conf: torch.Tensor | np.ndarray, background: int = 0) -> dict[str, float]:
    """Foreground-vs-background accuracy, precision, recall and F1 of the foreground class.

    A multi-class matrix (e.g. 6 parts + background) is first collapsed to 2 classes, every
    non-background class counting as foreground, so thesis Table 6.4's fg-vs-bg and part scores
    both come from one accumulated matrix.

    Args:
        conf: (C, C) counts, rows target, columns prediction, C >= 2.
        background: the index of the background class.

    Returns:
        ``{"accuracy", "precision", "recall", "f1"}`` as floats; F1 is that of the foreground class
        (NaN where neither the target nor the prediction has any foreground).

    Raises:
        ValueError: on a bad matrix or a background index outside [0, C).
    """
    c = _check_confusion(conf)
    if c.shape[0] < 2:
        raise ValueError(f"conf needs at least 2 classes (background and foreground), got {c.shape[0]}")
    if not 0 <= background < c.shape[0]:
        raise ValueError(f"background must be a class index in [0, {c.shape[0]}), got {background}")
    fg = torch.ones(c.shape[0], dtype=torch.bool)
    fg[background] = False
    tp = float(c[fg][:, fg].sum())
    fn = float(c[fg][:, ~fg].sum())
    fp = float(c[~fg][:, fg].sum())
    tn = float(c[~fg][:, ~fg].sum())
    total = tp + fn + fp + tn
    nan = float("nan")
    return {
        "accuracy": (tp + tn) / total if total > 0 else nan,
        "precision": tp / (tp + fp) if tp + fp > 0 else nan,
        "recall": tp / (tp + fn) if tp + fn > 0 else nan,
        "f1": 2 * tp / (2 * tp + fp + fn) if 2 * tp + fp + fn > 0 else nan,
    }


def vertex_error_mm(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(N,) mean Euclidean vertex error per mesh, millimetres (:func:`mpjpe` of the vertices)."""
    return mpjpe(pred, target) * 1000.0
