"""Checkpoint files: what a run's ``last.pt`` / ``best.pt``, an exported network and the packaged
``default`` hold, and how they are written and read.

A checkpoint is a dict of tensors, numbers, strings and containers only (``format``, ``version``,
``task``, ``config`` as plain data, the modules' state dicts, ...), written by ``torch.save`` and
read back with ``weights_only=True``. It holds no pickled class, so no module path of ``recovery``
is stored in it: moving a module (issue 33 moved most of them) never stops an older checkpoint from
loading, and no module-path mapping is needed (``tests/recovery/test_checkpoint.py`` loads the
packaged checkpoint, written before the move, and checks that a new one names no ``recovery``
global).
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path
from typing import Any

import torch

CHECKPOINT_FORMAT = "recovery-checkpoint"
CHECKPOINT_VERSION = 1


def save_atomic(obj: Any, path: Path) -> None:
    """``torch.save`` into a hidden temporary file beside ``path``, then rename (never a partial file)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        torch.save(obj, tmp)
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


DEFAULT_CHECKPOINT = Path(__file__).parent / "weights" / "hmr_blsm_default.pt"
"""The packaged HMR-BLSM (``recovery export``; how it was trained: docs/recovery.md)."""


def resolve(checkpoint: str | Path) -> Path:
    """A checkpoint's path: ``default`` is the packaged one."""
    return DEFAULT_CHECKPOINT if str(checkpoint) == "default" else Path(checkpoint)


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """Load a checkpoint file onto the CPU; a missing, corrupt or foreign file is a one-line ValueError."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such checkpoint")
    try:
        # weights_only: tensors, numbers, strings and containers only; a file that needs arbitrary
        # unpickling (code) is refused, never run
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any failure to read means a corrupt or refused file
        lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
        code = next((ln for ln in lines if "Unsupported global" in ln or "GLOBAL" in ln), None)
        if isinstance(exc, pickle.UnpicklingError) and code is not None:
            raise ValueError(f"{path}: refused: loading it would run code or unknown types ({code[:120]})") from None
        # random bytes also fail the weights-only unpickler ("Unsupported operand"): that is corruption
        what = next((ln for ln in lines if "Unsupported operand" in ln), lines[0] if lines else "")
        raise ValueError(f"{path}: corrupt checkpoint ({type(exc).__name__}: {what[:120]})") from None
    if not isinstance(ck, dict) or ck.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: not a {CHECKPOINT_FORMAT!r} file")
    if int(ck.get("version", -1)) != CHECKPOINT_VERSION:
        raise ValueError(f"{path}: checkpoint version {ck.get('version')} (this code reads {CHECKPOINT_VERSION})")
    return ck


def module_state(ck: dict[str, Any], name: str = "model") -> dict[str, torch.Tensor]:
    """Module ``name``'s state dict of a checkpoint, floating tensors in float32 (an exported
    checkpoint stores float16)."""
    return {k: v.float() if v.is_floating_point() else v for k, v in ck["modules"][name].items()}


def network_hash(ck: dict[str, Any]) -> str | None:
    """The checkpoint's network as today's config defines it (:meth:`recovery.config.RecoveryConfig.model_hash`
    of its stored config), so that a setting later left out of the hash (``model.train_blocks``) does not
    make the same network another; the stored ``model_hash`` where the config cannot be read."""
    from recovery.config import config_from_json

    try:
        return config_from_json({"task": ck["task"], **ck["config"]}, "checkpoint").model_hash()
    except (KeyError, TypeError, ValueError):
        return ck.get("model_hash")


def average_checkpoints(parts: list[tuple[str | Path, float]], dst: str | Path) -> Path:
    """Write the weighted mean of the networks of ``parts`` (``(checkpoint, weight)``; ``default``
    allowed) as an inference checkpoint: WiSE-FT (Wortsman et al., CVPR 2022) for a network and its
    own fine-tune, a model soup (Wortsman et al., ICML 2022) for several fine-tunes of one start.

    Every floating-point tensor of the network (BatchNorm statistics included) is the weighted mean;
    integer counters are the first network's; the config is the last one's. The networks must be
    the same (``model_hash``) for the same BLSM model file.

    Raises:
        ValueError: one line naming the file: unreadable, another network or BLSM model, no
            positive total weight.
    """
    if not parts or sum(w for _, w in parts) <= 0 or any(w < 0 for _, w in parts):
        raise ValueError(f"{dst}: weights must be >= 0 with a positive sum")
    cks = [(read_checkpoint(resolve(p)), float(w)) for p, w in parts]
    ref = cks[0][0]
    for (ck, _), (p, _) in zip(cks, parts, strict=False):
        if network_hash(ck) != network_hash(ref) or ck["blsm_model_sha256"] != ref["blsm_model_sha256"]:
            raise ValueError(f"{resolve(p)}: another network or BLSM model than {resolve(parts[0][0])}")
    total = sum(w for _, w in cks)
    state = {}
    for k, v in ref["modules"]["model"].items():
        state[k] = (sum(w * ck["modules"]["model"][k].float() for ck, w in cks) / total
                    if v.is_floating_point() else v)
    out = {k: ref.get(k) for k in ("format", "version", "task", "blsm_model_sha256", "model_hash", "step", "best", "saved")}
    out.update(config=cks[-1][0]["config"], modules={"model": state}, train_summary={},
               source=" + ".join(f"{w:g} x {p}" for p, w in parts))
    save_atomic(out, Path(dst))
    return Path(dst)
