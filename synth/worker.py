"""A worker of ``synth generate``: its state, loaded once, and the per-sample call.

Both engines run these functions in their worker processes: the process pool of
:func:`synth.generate.generate` (and that function's own process, with one worker) and the Ray
tasks of :mod:`synth.engine_ray`. :func:`init_worker` loads a worker's :class:`synth.sample.SampleMaker`
(the model, subjects, poses and backgrounds; scenes on first use); :func:`make_one` makes one
sample and returns a failure as data, so that the caller decides to stop or skip.

In a sequence run (:mod:`synth.sequence`) a unit of work is a sequence of ``sequence.frames``
samples: the worker makes a sequence's frames together when asked for its first and serves the
others from them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from synth.config import GeneratorConfig
from synth.dataset.shards import sample_rng
from synth.sample import SampleMaker
from synth.sequence import SequenceMaker, sequence_rng

Result = tuple[int, dict[str, bytes] | None, str, str]
"""``(index, fields, "", "")`` for a sample made, ``(index, None, error type, message)`` for one that
failed."""

_MAKER: SampleMaker | None = None
_SEQUENCES: SequenceMaker | None = None  # made on the first sequence
_ARGS: tuple = ()
_MADE = 0
_SEQUENCE: tuple[int, Any] = (-1, None)  # (sequence, its frames' fields or the exception that stopped it)


def frames_per_sample(cfg: GeneratorConfig) -> int:
    """Samples (frames) per unit of work: a sequence's frames, or 1 for single images."""
    return cfg.sequence.frames if cfg.sequence.enabled else 1


def init_worker(cfg_dict: dict, out: str, variant: str, threads: int, pool_worker: bool = False) -> None:
    """Load a worker's state once: the model, subjects, poses, backgrounds (scenes on first use).

    A pool worker also limits numpy's BLAS and OpenMP pools to one thread: their arrays are small,
    and idle BLAS threads spinning after each call took about 100 ms of CPU per image from the
    other worker (measured: 337 ms of CPU for 239 ms of wall time per image, 242 ms with one
    thread).
    """
    global _MAKER, _SEQUENCES, _ARGS, _MADE, _SEQUENCE
    import drjit as dr

    from synth.config import from_dict

    if pool_worker:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1)
    torch.set_num_threads(1)
    dr.set_thread_count(threads)
    _ARGS, _MADE, _SEQUENCE = (cfg_dict, out, variant, threads), 0, (-1, None)
    _MAKER, _SEQUENCES = SampleMaker(from_dict(GeneratorConfig, cfg_dict), Path(out), variant, threads), None


def make_one(index: int) -> Result:
    """Sample ``index`` (:data:`Result`). In a sequence run the worker makes a sequence's frames
    together when asked for its first and serves the others from them (the Ray engine asks for a
    shard's samples in order)."""
    global _SEQUENCE, _SEQUENCES
    if _MAKER is None:
        raise RuntimeError("make_one before init_worker")
    try:
        if not _MAKER.cfg.sequence.enabled:
            return index, _MAKER.make(index, sample_rng(_MAKER.cfg.seed, index)), "", ""
        seq, f = divmod(index, _MAKER.cfg.sequence.frames)
        if _SEQUENCE[0] != seq:
            _SEQUENCE = (seq, None)
            try:
                if _SEQUENCES is None:
                    _SEQUENCES = SequenceMaker(_MAKER)
                _SEQUENCE = (seq, _SEQUENCES.make(seq, sequence_rng(_MAKER.cfg.seed, seq)))
            except Exception as exc:  # every frame of the sequence reports it
                _SEQUENCE = (seq, exc)
        if isinstance(_SEQUENCE[1], Exception):
            raise _SEQUENCE[1]
        return index, _SEQUENCE[1][f], "", ""
    except Exception as exc:  # reported by the main process: stop, or skip with --skip-bad
        return index, None, type(exc).__name__, format_error(exc)


def make_sequence(seq: int) -> list[Result]:
    """Every frame of sequence ``seq`` (:func:`make_one`), for the process pool: one task a sequence."""
    if _MAKER is None:
        raise RuntimeError("make_sequence before init_worker")
    n = _MAKER.cfg.sequence.frames
    return [make_one(i) for i in range(seq * n, (seq + 1) * n)]


def make_in_process(index: int) -> Result:
    """:func:`make_one` in this process, rebuilding the worker state every ``recycle_after`` images
    (at a sequence's first frame in a sequence run)."""
    global _MADE
    if _MAKER is None:
        raise RuntimeError("make_in_process before init_worker")
    if _MADE >= _MAKER.cfg.render.recycle_after and index % frames_per_sample(_MAKER.cfg) == 0:
        init_worker(*_ARGS)
    _MADE += 1
    return make_one(index)


def format_error(exc: BaseException) -> str:
    """One line for the command line."""
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
