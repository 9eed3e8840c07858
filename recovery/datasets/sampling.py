"""The data order of a run: a seeded permutation per epoch that resumes from any position, its split
over the processes of a ``torchrun`` run, and evenly spread subsets.

Each item's augmentation is a function of ``(seed, epoch, item)`` only
(:class:`recovery.datasets.augment.BatchAugment`), and :class:`ResumableSampler` gives the order of
``(seed, epoch)`` from any position: a resumed run sees the same batches as an uninterrupted one;
:class:`ShardedBatches` splits each batch of that order over the processes (so the split changes
neither the batches nor, the augmentation being per item, the crops).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch


class ResumableSampler(torch.utils.data.Sampler):
    """Keys ``(epoch, i)`` of a seeded permutation per epoch, from item ``start`` of epoch ``epoch``."""

    def __init__(self, n: int, seed: int, epoch: int = 0, start: int = 0, shuffle: bool = True) -> None:
        self.n, self.seed, self.epoch, self.start, self.shuffle = n, seed, epoch, start, shuffle

    def order(self, epoch: int) -> np.ndarray:
        if not self.shuffle:
            return np.arange(self.n)
        return np.random.default_rng([self.seed, epoch]).permutation(self.n)

    def __iter__(self) -> Iterator[tuple[int, int]]:
        epoch, start = self.epoch, self.start
        while True:
            for i in self.order(epoch)[start:]:
                yield epoch, int(i)
            epoch, start = epoch + 1, 0

    def __len__(self) -> int:  # endless; the trainer counts steps
        return 2**62


class ShardedBatches(torch.utils.data.Sampler):
    """One process' part of each batch of a global order (a ``batch_sampler``).

    Global batch ``s`` holds keys ``s B .. s B + B - 1`` of ``sampler`` (B = ``batch_size``, the
    global batch); rank ``r`` of ``W`` processes takes its contiguous ``B / W`` of them. So the
    ranks' parts of step ``s`` together are the single-process batch of step ``s``, in order, for any
    ``W`` dividing ``B``; with ``W = 1`` these are ``DataLoader(batch_size=B, sampler=sampler)``'s
    batches.
    """

    def __init__(self, sampler: torch.utils.data.Sampler, batch_size: int, rank: int = 0,
                 world_size: int = 1) -> None:
        if batch_size % world_size:
            raise ValueError(f"train.batch_size {batch_size} (the global batch) must be divisible by the "
                             f"{world_size} processes")
        if not 0 <= rank < world_size:
            raise ValueError(f"rank {rank} outside 0 .. {world_size - 1}")
        self.sampler, self.batch_size, self.rank, self.world_size = sampler, batch_size, rank, world_size

    def __iter__(self) -> Iterator[list[Any]]:
        part = self.batch_size // self.world_size
        keys = iter(self.sampler)
        while True:
            batch = list(itertools.islice(keys, self.batch_size))
            if len(batch) < self.batch_size:
                return
            yield batch[self.rank * part : (self.rank + 1) * part]

    def __len__(self) -> int:
        return len(self.sampler) // self.batch_size


def spread_indices(n: int, k: int) -> np.ndarray:
    """``k`` indices spread evenly over ``range(n)`` (all when ``k`` is 0 or >= n)."""
    if k <= 0 or k >= n:
        return np.arange(n)
    return np.unique(np.floor(np.arange(k) * (n / k)).astype(np.int64))
