"""BLSM-spiral's shape space: ``V_s = D(z)`` (paper 000 Eq. 11, thesis Eq. 5.11) and its place in the model file.

:class:`SpiralShapeDecoder` replaces the linear ``V_s = c_s P_s`` (Eq. 8) through
:meth:`blsm.BLSM.set_shape_decoder`: ``forward(z)`` maps a latent code z (B, L) to the T-pose shape
offsets (B, V, 3) in metres, added to the template like any shape blendshape (Eq. 1). Inside, the
spiral decoder of :mod:`blsm.spiral.decoder` outputs *normalised* offsets (the paper's "normalised
deformations"); they are scaled back per vertex and coordinate by the training residuals' standard
deviation and mean (:class:`blsm.spiral.decoder.MeshNormalizer`).

In a model file (:func:`decoder_arrays`, :func:`decoder_from_arrays`) the decoder is the metadata
entry ``shape_decoder`` ``{"kind": "spiral", "latent": L, "channels": [...], "levels": n, ...}``
and arrays named ``shape_decoder__*``: the hierarchy (spiral indices, ``Q^d`` gathers, ``Q^u``
gathers and weights per level), the normaliser and the network's parameters, and the latent codes of
the training bodies (``shape_decoder__population``, which become ``population_shape``). Nothing
is rebuilt on load, so a loaded decoder gives the same vertices as the saved one to the bit.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from blsm.io import SHAPE_DECODER_PREFIX
from blsm.spiral.decoder import MeshNormalizer, SpiralDecoder
from blsm.spiral.hierarchy import MeshOperators
from blsm.spiral.sampling import Level

KIND = "spiral"
PREFIX = SHAPE_DECODER_PREFIX  # the arrays blsm.io keeps besides its own


class SpiralShapeDecoder(nn.Module):
    """``V_s = D(z)`` (Eq. 11): (B, L) latent codes -> (B, V, 3) T-pose offsets in metres.

    Args:
        ops: the template's hierarchy (levels and spirals, :mod:`blsm.spiral.hierarchy`).
        latent: L, the size of the code.
        channels: widths of the spiral convolutions per level, fine to coarse (``len(ops.levels)``).
        mean, std: (V, 3) the training residuals' per-vertex mean and standard deviation (metres).
    """

    def __init__(self, ops: MeshOperators, latent: int, channels: Sequence[int], mean: torch.Tensor,
                 std: torch.Tensor) -> None:
        super().__init__()
        if latent < 1:
            raise ValueError(f"latent must be >= 1, got {latent}")
        self.latent = int(latent)
        self.channels = tuple(int(c) for c in channels)
        self.decoder = SpiralDecoder(ops, self.channels, self.latent)
        # a floor of 0.1 mm: vertices that never move are not blown up by the normalisation
        self.normalizer = MeshNormalizer(mean, std, eps=1e-4)

    @property
    def num_coeffs(self) -> int:
        return self.latent

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """(B, L) codes -> (B, V, 3) offsets (metres)."""
        if z.dim() != 2 or z.shape[1] != self.latent:
            raise ValueError(f"latent codes must be (B, {self.latent}), got {tuple(z.shape)}")
        return self.normalizer.inverse(self.decoder(z))


def decoder_arrays(dec: SpiralShapeDecoder, ops: MeshOperators, population: torch.Tensor,
                   report: dict[str, Any] | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The model-file arrays and the ``shape_decoder`` metadata entry of a decoder (module docstring).

    Args:
        dec: the decoder. ops: the hierarchy it was built on.
        population: (N, L) the training bodies' codes.
        report: training numbers kept in the metadata.
    """
    arrays: dict[str, np.ndarray] = {}
    for i, lv in enumerate(ops.levels):
        arrays[f"{PREFIX}spiral_{i}"] = np.asarray(ops.spirals[i], dtype=np.int32)
        arrays[f"{PREFIX}down_{i}"] = np.asarray(lv.down, dtype=np.int32)
        arrays[f"{PREFIX}up_index_{i}"] = np.asarray(lv.up_index, dtype=np.int32)
        arrays[f"{PREFIX}up_weight_{i}"] = np.asarray(lv.up_weight, dtype=np.float32)
    arrays[f"{PREFIX}mean"] = dec.normalizer.mean.detach().cpu().float().numpy()
    arrays[f"{PREFIX}std"] = dec.normalizer.std.detach().cpu().float().numpy()
    for name, p in dec.decoder.named_parameters():
        arrays[f"{PREFIX}param.{name}"] = p.detach().cpu().float().numpy()
    arrays[f"{PREFIX}population"] = population.detach().cpu().float().numpy()
    meta = {"kind": KIND, "latent": dec.latent, "channels": list(dec.channels), "levels": len(ops.levels),
            "report": report or {}}
    return arrays, meta


def decoder_from_arrays(arrays: dict[str, np.ndarray], meta: Any, where: str) -> tuple[SpiralShapeDecoder, torch.Tensor]:
    """Rebuild the decoder of a model file; returns it (float32) and the (N, L) population codes.

    Raises:
        ValueError: naming ``where`` on an unknown kind or a missing or mis-shaped array.
    """
    if not isinstance(meta, dict) or meta.get("kind") != KIND:
        kind = meta.get("kind") if isinstance(meta, dict) else meta
        raise ValueError(f"{where}: shape_decoder kind {kind!r} is not supported (known: {KIND!r})")

    def get(name: str) -> np.ndarray:
        key = PREFIX + name
        if key not in arrays:
            raise ValueError(f"{where}: the spiral shape decoder needs array {key!r}")
        return arrays[key]

    try:
        n, latent, channels = int(meta["levels"]), int(meta["latent"]), [int(c) for c in meta["channels"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{where}: bad shape_decoder metadata ({exc})") from None
    levels = [Level(down=get(f"down_{i}").astype(np.int64), up_index=get(f"up_index_{i}").astype(np.int64),
                    up_weight=get(f"up_weight_{i}"), faces=np.zeros((0, 3), np.int64)) for i in range(n)]
    spirals = [get(f"spiral_{i}").astype(np.int64) for i in range(n)]
    mean = torch.as_tensor(get("mean"))
    ops = MeshOperators(levels=levels, spirals=spirals, faces=[], reference=np.zeros((len(mean), 3), np.float32),
                        regressor=np.zeros((0, len(mean)), np.float32), keypoint_names=[],
                        regressor_error_mm=0.0, model_sha256="")
    dec = SpiralShapeDecoder(ops, latent, channels, mean, torch.as_tensor(get("std")))
    state = dec.decoder.state_dict()
    for name, p in dec.decoder.named_parameters():
        value = torch.as_tensor(get(f"param.{name}"))
        if value.shape != p.shape:
            raise ValueError(f"{where}: {PREFIX}param.{name} is {tuple(value.shape)}, expected {tuple(p.shape)}")
        state[name] = value
    dec.decoder.load_state_dict(state)
    dec.normalizer.std.copy_(torch.as_tensor(get("std")))  # stored after the floor: exactly as saved
    population = torch.as_tensor(get("population"), dtype=torch.float32)
    if population.dim() != 2 or population.shape[1] != latent:
        raise ValueError(f"{where}: {PREFIX}population must be (N, {latent}), got {tuple(population.shape)}")
    return dec, population
