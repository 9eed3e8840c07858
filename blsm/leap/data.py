"""Training and test data for LEAP on BLSM (issue 55): posed bodies of the model's population and
the query points LEAP learns from, with their exact occupancy and pseudo ground-truth weights.

- **Bodies.** A subject is a row of the model's population (``population_bone``,
  ``population_shape``); a pose is a frame of a motion clip (``blsm mocap import``), its root
  rotation kept and the root at the origin. **Splits** as the paper's Sec. 6.3: unseen subjects
  are every tenth population row (:func:`subject_split`); unseen poses are whole clips left out
  (``held_out`` clip names: other actions than those trained on).
- **Points** (Sec. 6, "Experimental setup"): half uniform in the body's box grown by 10 %, half
  normal around surface points (:func:`blsm.occupancy.sample_points`); occupancy by the exact
  winding number (:func:`blsm.occupancy.inside`, right also where a pose makes the mesh pass
  through itself, where a pseudonormal sign is not); pseudo ground-truth
  skinning weights of a point are those of its nearest mesh vertex (Sec. 4.3), posed for the
  inverse LBS network and canonical (template) for the forward one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from blsm import occupancy


def subject_split(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(train, unseen) population rows: every tenth row (9, 19, ...) is unseen (Sec. 6.3 leaves out
    every 10-th subject)."""
    rows = np.arange(n)
    return rows[rows % 10 != 9], rows[rows % 10 == 9]


def load_clips(folder: str | Path, names: list[str] | None = None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{clip: (pose (T, 47), global_orient (T, 3))}`` of an imported motion library folder."""
    out = {}
    for path in sorted(Path(folder).glob("*.npz")):
        if names is not None and path.stem not in names:
            continue
        with np.load(path, allow_pickle=False) as d:
            out[path.stem] = (d["pose"].astype(np.float32), d["global_orient"].astype(np.float32))
    if not out:
        raise ValueError(f"{folder}: no motion clips (*.npz from blsm mocap import)" + (f" named {names}" if names else ""))
    return out


@dataclass
class Bodies:
    """Posed bodies: ``B`` (N, K, 3, 4) local transforms (Eq. 8; BLSM's skinning transforms),
    ``vertices`` (N, V, 3) posed, ``template`` (N, V, 3) canonical, ``shape`` (N, Ks) the identity
    coefficients, ``subject`` (N,) population rows, ``clip`` and ``frame`` where the pose came from."""

    B: np.ndarray
    vertices: np.ndarray
    template: np.ndarray
    shape: np.ndarray
    subject: np.ndarray
    clip: list[str]
    frame: np.ndarray


def draw_bodies(model: torch.nn.Module, clips: dict[str, tuple[np.ndarray, np.ndarray]], subjects: np.ndarray, n: int,
                rng: np.random.Generator) -> Bodies:
    """``n`` bodies: subjects drawn from ``subjects`` (population rows), frames from ``clips``."""
    names = sorted(clips)
    subj = rng.choice(subjects, n)
    which = rng.integers(len(names), size=n)
    frames = np.array([rng.integers(len(clips[names[c]][0])) for c in which])
    pose = torch.from_numpy(np.stack([clips[names[c]][0][f] for c, f in zip(which, frames)]))
    orient = torch.from_numpy(np.stack([clips[names[c]][1][f] for c, f in zip(which, frames)]))
    bone, shape = model.population_bone[subj], model.population_shape[subj]
    with torch.no_grad():
        out = model(pose=pose, bone=bone, shape=shape, global_orient=orient)
    return Bodies(out.skinning_transforms.numpy(), out.vertices.numpy(), out.template.numpy(), shape.numpy(), subj,
                  [names[c] for c in which], frames)


def body_points(model: torch.nn.Module, vertices: np.ndarray, template: np.ndarray, n: int,
                rng: np.random.Generator) -> dict[str, np.ndarray]:
    """One body's query points (module docstring): ``x`` (n, 3) posed, ``occ`` (n,) 1 inside,
    ``w`` (n, K) the nearest posed vertex's weights; ``xc`` (n, 3) canonical points, ``wc``
    (n, K) the nearest template vertex's weights and ``occ_c`` (n,) 1 inside the template."""
    from scipy.spatial import cKDTree

    faces = model.faces.numpy()
    weights = model.weights.numpy()
    x = occupancy.sample_points(vertices, faces, n // 2, n - n // 2, rng)
    occ = occupancy.inside(x, vertices, faces)  # the exact winding number: right where a pose self-intersects
    w = weights[cKDTree(vertices).query(x)[1]]
    xc = occupancy.sample_points(template, faces, n // 2, n - n // 2, rng)
    wc = weights[cKDTree(template).query(xc)[1]]
    occ_c = occupancy.inside(xc, template, faces)
    f32 = np.float32
    return {"x": x.astype(f32), "occ": occ.astype(f32), "w": w.astype(f32), "xc": xc.astype(f32), "wc": wc.astype(f32),
            "occ_c": occ_c.astype(f32)}


def subject_templates(model: torch.nn.Module, subjects: np.ndarray) -> torch.Tensor:
    """(n, V, 3) the rest templates of the population rows ``subjects`` (n,)."""
    rows = torch.as_tensor(np.asarray(subjects), dtype=torch.long)
    with torch.no_grad():
        return model(bone=model.population_bone[rows], shape=model.population_shape[rows]).template


def canonical_occupancy(model: torch.nn.Module, subjects: np.ndarray, xc: np.ndarray) -> np.ndarray:
    """(n, m) 1 where the canonical points ``xc`` (n, m, 3) are inside their subjects' templates
    (the ``occ_c`` of :func:`body_points`, for a data file made before it was kept)."""
    templates = subject_templates(model, subjects).numpy()
    faces = model.faces.numpy()
    return np.stack([occupancy.inside(xc[i], templates[i], faces) for i in range(len(xc))]).astype(np.float32)
