"""Load a trained network for inference: a run's ``best.pt`` / ``last.pt``, an exported file, or
``default`` (the packaged checkpoint, :data:`DEFAULT_CHECKPOINT`).

A checkpoint names the BLSM model file it was trained with by its SHA-256; loading it with another
model file is an error (its parameters would mean other bodies), as is a file that is not a
checkpoint or whose weights do not fit the network its config describes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

import blsm
from blsm.io import sha256_file
from recovery.config import RecoveryConfig, config_from_json
from recovery.models.hmr import BodyOutput, HMRBLSM, HMROutput, predict_body
from recovery.trainer import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, read_checkpoint, save_atomic

DEFAULT_CHECKPOINT = Path(__file__).parent / "data" / "hmr_blsm_default.pt"
"""The packaged HMR-BLSM (``recovery export``; how it was trained: docs/recovery.md)."""


@dataclass
class Predictor:
    """A network ready for inference (eval mode) with its BLSM model and settings."""

    model: HMRBLSM
    body: torch.nn.Module
    config: RecoveryConfig
    path: Path
    info: dict[str, Any]

    @property
    def crop(self) -> int:
        return self.config.data.crop

    def to(self, device: torch.device | str) -> Predictor:
        self.model.to(device)
        self.body.to(device)
        return self

    @torch.no_grad()
    def __call__(self, images: torch.Tensor, k_crop: torch.Tensor) -> tuple[HMROutput, BodyOutput]:
        """(B, 3, crop, crop) RGB in [0, 1] and (B, 3, 3) ``K_crop`` -> parameters and the body."""
        dev = next(self.model.parameters()).device
        pred = self.model(images.to(dev))
        return pred, predict_body(self.body, pred, k_crop.to(dev), self.crop)


def resolve(checkpoint: str | Path) -> Path:
    return DEFAULT_CHECKPOINT if str(checkpoint) == "default" else Path(checkpoint)


def load_predictor(checkpoint: str | Path, model_path: str | Path | None = None) -> Predictor:
    """The network of a checkpoint (``default`` for the packaged one), in eval mode on the CPU.

    Args:
        checkpoint: a checkpoint file or ``default``.
        model_path: the BLSM model file (default: the one in the checkpoint's config, else the packaged one).

    Raises:
        ValueError: one line naming the file: missing, corrupt, another task, made for another
            model file, or weights that do not fit its config.
    """
    from recovery.hmr_task import build_model
    from recovery.train import model_file

    path = resolve(checkpoint)
    ck = read_checkpoint(path)
    if ck.get("task") != "hmr_blsm":
        raise ValueError(f"{path}: a checkpoint of task {ck.get('task')!r}; this command reads hmr_blsm")
    cfg = config_from_json(ck["config"], str(path))
    mpath = Path(model_path) if model_path else model_file(cfg)
    if not mpath.is_file():
        raise ValueError(f"{mpath}: the BLSM model file of {path} is missing")
    if sha256_file(mpath) != ck.get("blsm_model_sha256"):
        raise ValueError(f"{path}: made for another BLSM model file than {mpath} (SHA-256 differs)")
    body = blsm.load(mpath)
    model = build_model(cfg, body, pretrained=False)
    state = {k: v.float() if v.is_floating_point() else v for k, v in ck["modules"]["model"].items()}
    try:
        model.load_state_dict(state)
    except RuntimeError as exc:
        raise ValueError(f"{path}: weights do not fit the network of its config ({str(exc).splitlines()[0][:160]})") from None
    model.eval()
    info = {k: ck.get(k) for k in ("step", "saved", "best", "train_summary")}
    return Predictor(model=model, body=body, config=cfg, path=path, info=info)


def export(src: str | Path, dst: str | Path, half: bool = True, summary: dict[str, Any] | None = None) -> Path:
    """Write an inference-only copy of a run's checkpoint (the network's weights, float16 when
    ``half``, its config and model hash; no optimiser or discriminator state)."""
    src, dst = Path(src), Path(dst)
    ck = read_checkpoint(src)
    weights = {k: (v.half() if half and v.is_floating_point() else v) for k, v in ck["modules"]["model"].items()}
    out = {
        "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "task": ck["task"], "config": ck["config"],
        "blsm_model_sha256": ck["blsm_model_sha256"], "model_hash": ck.get("model_hash"),
        "step": ck["step"], "best": ck.get("best"), "saved": ck.get("saved"), "source": str(src),
        "modules": {"model": weights}, "train_summary": summary or {},
    }
    save_atomic(out, dst)
    return dst
