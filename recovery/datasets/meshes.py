"""Mesh data without rendering (thesis Sec. 4.5.2, issue "Recovery II" item 3); the PCA baseline fitted
on these meshes is :class:`recovery.models.pca.PCAModel`.

A mesh is the BLSM body of one member of the model's population (its bone and shape coefficients)
in one pose, with the global orientation removed as in Sec. 4.5.2: zero global rotation and the
pelvis (root joint) at the origin — the body frame (metres, Y up, facing +Z). Splits never share
people or motions:

- **train**: the first ``train`` fraction of the population; poses from the packaged pose prior
  (fitted without the test clips) and, with ``library``, frames of the training motion library;
- **val**: the next people, prior poses (model selection);
- **test**: the remaining people posed with the frames of the held-out clips (``test_library``,
  the clips the prior and the training library leave out: 007_12 and 005_20).

Batches are a function of ``(seed, batch index)`` only, so a run resumes with the same meshes and
draws "as many as training wants".
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch
from torch import nn

from recovery.config import MeshDataConfig


def _library_poses(folder: str, exclude: tuple[str, ...], keep_only: tuple[str, ...] | None = None) -> torch.Tensor:
    from blsm.mocap.library import list_clips, load_clip

    path = Path(folder)
    if not path.is_dir():
        raise ValueError(f"{path}: no such motion library folder (make it with `blsm mocap import`)")
    chunks = []
    for f in list_clips(path):
        if keep_only is not None and f.stem not in keep_only:
            continue
        if keep_only is None and f.stem in exclude:
            raise ValueError(f"{f}: clip {f.stem} is held out for testing and must not be in a training library")
        chunks.append(torch.as_tensor(load_clip(f).pose, dtype=torch.float32))
    if not chunks:
        raise ValueError(f"{path}: no usable clips")
    return torch.cat(chunks)


class MeshSource:
    """Draws (pose, bone, shape) of one split (module docstring).

    Args:
        body: the BLSM model. cfg: the mesh data settings. split: "train", "val" or "test" (whose
            people). poses: "split" (the split's poses, module docstring) or "prior" (pose-prior draws
            only: the test people in the prior's whole range, harder than the held-out clips).
    """

    def __init__(self, body: nn.Module, cfg: MeshDataConfig, split: str, poses: str = "split") -> None:
        if split not in ("train", "val", "test"):
            raise ValueError(f"split must be train, val or test, got {split!r}")
        if poses not in ("split", "prior"):
            raise ValueError(f"poses must be split or prior, got {poses!r}")
        self.body, self.cfg, self.split, self.poses = body, cfg, split, poses
        n = body.population_bone.shape[0]
        a, b = int(round(cfg.train * n)), int(round((cfg.train + cfg.val) * n))
        self.people = {"train": torch.arange(0, a), "val": torch.arange(a, b), "test": torch.arange(b, n)}[split]
        if len(self.people) == 0:
            raise ValueError(f"the {split} split of {n} population members is empty")
        self.library: torch.Tensor | None = None
        self.prior = None
        if split == "test" and poses == "split":
            self.library = _library_poses(cfg.test_library, (), keep_only=cfg.exclude_clips)
        else:
            from blsm.mocap.prior import DEFAULT_PRIOR, load_prior

            self.prior = load_prior(DEFAULT_PRIOR)
            if split == "train" and poses == "split" and cfg.library and cfg.library_share > 0:
                self.library = _library_poses(cfg.library, cfg.exclude_clips)

    def sample(self, n: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """``n`` draws: ``pose`` (n, 47) unconstrained, ``bone`` (n, Kb), ``shape`` (n, Ks)."""
        who = self.people[torch.randint(0, len(self.people), (n,), generator=generator)]
        if self.prior is None:
            pose = self.library[torch.randint(0, len(self.library), (n,), generator=generator)]
        else:
            pose = self.prior.sample(n, generator).float()
            if self.library is not None:
                use = torch.rand(n, generator=generator) < self.cfg.library_share
                frames = self.library[torch.randint(0, len(self.library), (n,), generator=generator)]
                pose = torch.where(use[:, None], frames, pose)
        return {"pose": pose, "bone": self.body.population_bone[who].float().cpu(),
                "shape": self.body.population_shape[who].float().cpu()}


def body_frame_vertices(body: nn.Module, pose: torch.Tensor, bone: torch.Tensor, shape: torch.Tensor) -> torch.Tensor:
    """(B, V, 3) BLSM vertices with no global rotation, the pelvis at the origin (metres)."""
    out = body(pose=pose, bone=bone, shape=shape)
    return out.vertices - out.joints[:, :1]


def mesh_batches(source: MeshSource, batch_size: int, seed: int, start: int = 0) -> Iterator[dict[str, torch.Tensor]]:
    """Endless batches; batch ``i`` depends only on ``(seed, i)``. ``key`` holds the draw indices."""
    i = start
    while True:
        g = torch.Generator().manual_seed(int(seed) * 1_000_003 + i)
        batch = source.sample(batch_size, g)
        batch["key"] = torch.arange(i * batch_size, (i + 1) * batch_size)
        yield batch
        i += 1


def fixed_meshes(body: nn.Module, source: MeshSource, n: int, seed: int, batch: int = 256) -> torch.Tensor:
    """(n, V, 3) body-frame meshes drawn once (validation, test, statistics, PCA)."""
    g = torch.Generator().manual_seed(seed)
    out = []
    with torch.no_grad():
        for k in range(0, n, batch):
            p = source.sample(min(batch, n - k), g)
            out.append(body_frame_vertices(body, p["pose"], p["bone"], p["shape"]))
    return torch.cat(out)


def vertex_stats(meshes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-vertex, per-coordinate mean and standard deviation (V, 3) of training meshes (N, V, 3)."""
    return meshes.mean(0), meshes.std(0)


def describe(source: MeshSource) -> dict[str, Any]:
    return {"split": source.split, "people": len(source.people),
            "poses": "prior" if source.poses == "prior"
            else "held-out clips " + ", ".join(source.cfg.exclude_clips) if source.split == "test"
            else ("prior" + (f" + library {source.cfg.library} ({source.cfg.library_share:.0%})" if source.library is not None else ""))}
