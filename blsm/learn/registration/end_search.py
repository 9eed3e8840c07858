"""Grid searches of the hands' and feet's orientation for the registration from keypoints
(:func:`blsm.learn.registration.register.register_keypoints`, thesis Sec. 6.3; an engineering addition).

BlazePose's keypoints stop at the wrist and give the foot only a heel and a toe point 2-3 cm off, so
Eq. 6.4 leaves the wrist and forearm twist at 0 and the ankle loosely fitted, and the mutual nearest
neighbours of Eq. 6.5 barely turn a hand or a foot. These searches try a grid of the end bone's
angles per frame and side and keep the combination closest to the scan (docs/markerless.md).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from blsm.learn.posing import pose
from blsm.learn.registration.keypoint_fit import KeypointFit

# Wrist and forearm angles tried by :func:`search_hands` (radians): the detectors give no hand
# orientation (MediaPipe's wrist only), so the keypoint fit leaves them at 0.
HAND_GRID: dict[str, tuple[float, ...]] = {
    "wrist_{s}.flex": (-0.9, -0.45, 0.0, 0.45, 0.9),
    "wrist_{s}.deviate": (-0.35, 0.0, 0.35),
    "elbow_{s}.pronate": (-0.7, 0.0, 0.7),
}


# Steps tried around the current angles by :func:`search_hands` with ``around=True``, once Eq. 6.5
# has fitted the shape (``KeypointFitConfig.hand_search_round``): a finer grid than HAND_GRID's.
HAND_GRID_FINE: dict[str, tuple[float, ...]] = {
    "wrist_{s}.flex": (-0.3, -0.15, 0.0, 0.15, 0.3),
    "wrist_{s}.deviate": (-0.15, 0.0, 0.15),
    "elbow_{s}.pronate": (-0.3, 0.0, 0.3),
}

# The same for the feet (:func:`search_feet`): heel and toe keypoints give the foot a start, but
# BlazePose places them 2-3 cm off (docs/markerless.md), so the ankle is searched around the fit.
FOOT_GRID_FINE: dict[str, tuple[float, ...]] = {
    "ankle_{s}.plantarflex": (-0.3, -0.15, 0.0, 0.15, 0.3),
    "ankle_{s}.invert": (-0.15, 0.0, 0.15),
    "ankle_{s}.abduct": (-0.15, 0.0, 0.15),
}


def search_hands(model, fit: KeypointFit, scans: Sequence[tuple[np.ndarray, np.ndarray]],
                 cap: float = 0.05, reach: float = 0.22, around: bool = False) -> KeypointFit:
    """Each hand's wrist flexion/deviation and forearm pronation from a grid (:data:`HAND_GRID`):
    per frame and side, the combination with the smallest local chamfer distance (capped at ``cap``
    metres): hand vertices to the scan, plus the scan vertices within ``reach`` of the wrist joint to
    the nearer of that hand and the rest of the body. The surface fit (Eq. 6.5) then refines it;
    started at 0, its mutual nearest neighbours do not reach a hand bent by 40 degrees.

    With ``around=True`` the grid is :data:`HAND_GRID_FINE`, added to the fit's current angles (a
    second search once the shape is fitted), and the current angles are among the candidates.

    Returns:
        The fit with those angles replaced (inside the limits).
    """
    grid = HAND_GRID_FINE if around else HAND_GRID
    return _search_end(model, fit, scans, "wrist_{s}", grid, around, cap, reach)


def search_feet(model, fit: KeypointFit, scans: Sequence[tuple[np.ndarray, np.ndarray]],
                cap: float = 0.05, reach: float = 0.25) -> KeypointFit:
    """Each foot's ankle angles around the fit (:data:`FOOT_GRID_FINE`), scored as
    :func:`search_hands` scores a hand (the foot bone's vertices and the scan within ``reach`` of
    the ankle joint); the current angles are among the candidates."""
    return _search_end(model, fit, scans, "ankle_{s}", FOOT_GRID_FINE, True, cap, reach)


def _search_end(model, fit: KeypointFit, scans, bone: str, grid: dict[str, tuple[float, ...]], around: bool,
                cap: float, reach: float) -> KeypointFit:
    """The grid search of :func:`search_hands` for the end bone ``bone`` (``{s}``: l, r) of each side."""
    import itertools

    from scipy.spatial import cKDTree

    angles = fit.angles.clone()
    offs, b = fit.offsets(model), fit.bone_scales(model)
    lim = model.dof_limits.to(angles.dtype)
    steps = torch.tensor(list(itertools.product(*grid.values())), dtype=angles.dtype)  # (C, 3)
    sides = []  # per side: the grid's dof indices, the end bone, its vertices
    for side in ("l", "r"):
        names = [k.format(s=side) for k in grid]
        if all(n in model.dof_names for n in names):
            j = model.bone_names.index(bone.format(s=side))
            sides.append(([model.dof_names.index(n) for n in names], j, model.vertex_bones == j))
    for t, (sv, _) in enumerate(scans):
        sv = np.asarray(sv, np.float64)
        tree = cKDTree(sv)
        for idx, j, is_end in sides:
            combos = steps + angles[t, idx] if around else steps
            cand = angles[t:t + 1].repeat(len(combos), 1)
            cand[:, idx] = torch.maximum(torch.minimum(combos, lim[idx, 1]), lim[idx, 0])
            with torch.no_grad():
                p = pose(model, model.template + offs[t], bone_scales=b[t:t + 1], angles=cand,
                         global_orient=fit.global_orient[t:t + 1], transl=fit.transl[t:t + 1])
            ends = p.vertices[:, is_end].double().numpy()  # (C, H, 3)
            centre = p.joints[0, j].double().numpy()
            local = sv[np.linalg.norm(sv - centre, axis=1) < reach]  # scan near the end
            rest = np.minimum(cKDTree(p.vertices[0, ~is_end].double().numpy()).query(local, k=1)[0], cap)
            cost = np.zeros(len(combos))
            for c in range(len(combos)):
                d_h = np.minimum(tree.query(ends[c], k=1, distance_upper_bound=cap)[0], cap).mean()
                d_s = np.minimum(cKDTree(ends[c]).query(local, k=1, distance_upper_bound=cap)[0], rest)
                cost[c] = d_h + (d_s.mean() if len(local) else 0.0)
            angles[t] = cand[int(np.argmin(cost))]
    return KeypointFit(fit.groups, fit.bone, fit.shape, angles, fit.global_orient, fit.transl,
                       fit.keypoint_error)
