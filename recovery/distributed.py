"""Training on several processes (``torchrun``): the process group, reductions across processes, and
a SyncBatchNorm that also runs on the CPU.

``recovery train`` reads torchrun's ``WORLD_SIZE``, ``RANK`` and ``LOCAL_RANK``; without them (or
with ``WORLD_SIZE=1``) every function here is the identity and a run is exactly the single-process
run. With ``W > 1`` processes the process group uses gloo on the CPU and NCCL on CUDA (one GPU per
process, ``cuda:LOCAL_RANK``).

The convention of the reductions is DistributedDataParallel's: DDP averages gradients over the
ranks, so each rank's loss is its *share scaled by W*, a tensor whose mean over the ranks is the
global loss (a plain mean over the rank's equal part of the batch already is one; a loss normalised
by a data-dependent count divides by the count summed over the ranks, over W). The mean of the
ranks' gradients is then the gradient of the global loss.

torch's ``nn.SyncBatchNorm`` refuses CPU tensors ("expected input tensor to be on GPU"; torch
2.13) and DDP refuses it in a CPU module, so on the CPU :class:`CPUSyncBatchNorm` computes the
batch statistics itself with one differentiable all-reduce of the per-channel sums (float64); on
CUDA torch's own layer is used.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np
import torch
import torch.distributed as dist
from torch import nn


@dataclass(frozen=True)
class DistEnv:
    """Where this process stands among torchrun's processes.

    Attributes:
        rank: this process, 0 .. world_size - 1 (rank 0 writes checkpoints and logs).
        world_size: processes in all (1: a plain run).
        local_rank: this process on its machine (its GPU index on CUDA).
    """

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        """Rank 0: the process that writes files and prints."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


SINGLE = DistEnv()


def from_environment(environ: Mapping[str, str] | None = None) -> DistEnv:
    """The :class:`DistEnv` of torchrun's ``WORLD_SIZE`` / ``RANK`` / ``LOCAL_RANK`` (a plain run
    without them)."""
    environ = os.environ if environ is None else environ
    if "WORLD_SIZE" not in environ:
        return SINGLE
    try:
        world = int(environ["WORLD_SIZE"])
        rank = int(environ.get("RANK", "0"))
        local = int(environ.get("LOCAL_RANK", str(rank)))
    except ValueError:
        raise ValueError("WORLD_SIZE, RANK and LOCAL_RANK must be integers (set by torchrun)") from None
    if world < 1 or not 0 <= rank < world or local < 0:
        raise ValueError(f"bad torchrun environment: WORLD_SIZE {world}, RANK {rank}, LOCAL_RANK {local}")
    return DistEnv(rank=rank, world_size=world, local_rank=local)


def init(env: DistEnv, device: torch.device) -> torch.device:
    """Join the process group (gloo on the CPU, NCCL on CUDA); returns this process' device.

    Nothing happens for a single process. Rendezvous comes from torchrun's ``MASTER_ADDR`` and
    ``MASTER_PORT``.
    """
    if not env.distributed:
        return device
    if device.type == "cuda":
        if env.local_rank >= torch.cuda.device_count():
            raise ValueError(f"LOCAL_RANK {env.local_rank} but only {torch.cuda.device_count()} CUDA devices "
                             "here; use --nproc-per-node at most the number of GPUs")
        device = torch.device("cuda", env.local_rank)
        torch.cuda.set_device(device)
    if not dist.is_initialized():
        if device.type == "cuda":
            dist.init_process_group("nccl", rank=env.rank, world_size=env.world_size, device_id=device)
        else:
            dist.init_process_group("gloo", rank=env.rank, world_size=env.world_size)
    return device


def shutdown() -> None:
    """Leave the process group (if any)."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def world_size() -> int:
    """Processes in the current group (1 without one)."""
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def barrier() -> None:
    if world_size() > 1:
        dist.barrier()


def all_sum(x: torch.Tensor) -> torch.Tensor:
    """The sum of ``x`` over the processes (a new tensor, no gradient; ``x`` itself for one)."""
    if world_size() == 1:
        return x
    y = x.detach().clone()
    dist.all_reduce(y)
    return y


def rank_mean(x: torch.Tensor) -> torch.Tensor:
    """The mean of ``x`` over the processes (``x`` itself for one): the global value of a loss
    given as per-rank shares (module docstring)."""
    w = world_size()
    return x if w == 1 else all_sum(x) / w


def share_normaliser(count: torch.Tensor) -> torch.Tensor:
    """The divisor that turns one rank's sum into its share of a mean normalised by a data-dependent
    ``count`` (e.g. the visible keypoints): ``max(sum of count over ranks, 1) / W``.

    For one process this is ``max(count, 1)``: the plain normalisation.
    """
    w = world_size()
    return all_sum(count.detach()).clamp(min=1.0) / w if w > 1 else count.clamp(min=1.0)


def gather(x: torch.Tensor) -> torch.Tensor:
    """(n, ...) of every process concatenated in rank order (all ranks pass the same shape)."""
    w = world_size()
    if w == 1:
        return x
    parts = [torch.empty_like(x) for _ in range(w)]
    dist.all_gather(parts, x.contiguous())
    return torch.cat(parts)


class _AllSum(torch.autograd.Function):
    """Sum over the processes whose backward is the sum of the gradients over the processes: each
    rank's loss depends on every rank's input through the sum."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:  # noqa: ANN001
        y = x.clone(memory_format=torch.contiguous_format)
        dist.all_reduce(y)
        return y

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:  # noqa: ANN001
        g = grad.clone(memory_format=torch.contiguous_format)
        dist.all_reduce(g)
        return g


def all_sum_differentiable(x: torch.Tensor) -> torch.Tensor:
    """:func:`all_sum` that gradients flow through (module docstring)."""
    return x if world_size() == 1 else _AllSum.apply(x)


def average_gradients(params: Iterable[torch.Tensor]) -> None:
    """Replace each gradient by its mean over the processes (one all-reduce of a flat buffer); for a
    network stepped outside DDP. A parameter without a gradient counts as a zero gradient."""
    w = world_size()
    if w == 1:
        return
    params = [p for p in params if p.requires_grad]
    if not params:
        return
    flat = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in params])
    dist.all_reduce(flat)
    flat /= w
    n = 0
    for p in params:
        k = p.numel()
        p.grad = flat[n : n + k].view_as(p).clone()
        n += k


def rank_seed(seed: int, rank: int, step: int = 0) -> int:
    """A seed for rank ``rank``'s own random stream (dropout) from the run's seed and the step it
    starts at."""
    return int(np.random.SeedSequence([seed, rank, step, 0x5EED]).generate_state(1, np.uint64)[0] >> 1)


def sync_batch_norm(x: torch.Tensor, weight: torch.Tensor | None, bias: torch.Tensor | None,
                    running_mean: torch.Tensor | None, running_var: torch.Tensor | None, momentum: float,
                    eps: float) -> torch.Tensor:
    """Batch normalisation with the statistics of the batch of every process (training mode).

    One all-reduce of the per-channel count, sum and sum of squares, in float64 (so that the
    variance ``E[x^2] - E[x]^2`` loses nothing to cancellation); gradients flow through it to every
    process' input.

    Args:
        x: (B, C, ...) this rank's part of the batch.
        weight, bias: (C,) the affine map, or None.
        running_mean, running_var: (C,) updated in place (unbiased variance, as torch) when given.
        momentum: the running statistics' update factor.
        eps: added to the variance.

    Returns:
        (B, C, ...) as ``F.batch_norm`` of the concatenated batches, this rank's rows.
    """
    c = x.shape[1]
    dims = [0, *range(2, x.dim())]
    shape = (1, c) + (1,) * (x.dim() - 2)
    xd = x.double()
    count = xd.new_full((1,), x.numel() // c)
    total = all_sum_differentiable(torch.cat([xd.sum(dims), xd.square().sum(dims), count]))  # (2 C + 1,)
    n = total[2 * c].detach()
    mean = total[:c] / n
    var = (total[c : 2 * c] / n - mean.square()).clamp(min=0.0)  # biased, as the normalisation uses
    y = (x - mean.to(x.dtype).view(shape)) * torch.rsqrt(var + eps).to(x.dtype).view(shape)
    if weight is not None:
        y = y * weight.view(shape)
    if bias is not None:
        y = y + bias.view(shape)
    if running_mean is not None and running_var is not None:
        with torch.no_grad():
            running_mean.lerp_(mean.to(running_mean.dtype), momentum)
            unbiased = var * (n / (n - 1).clamp(min=1.0))
            running_var.lerp_(unbiased.to(running_var.dtype), momentum)
    return y


class CPUSyncBatchNorm(nn.modules.batchnorm._BatchNorm):
    """BatchNorm whose training statistics are those of every process' batch, on the CPU (gloo;
    :func:`sync_batch_norm`); a plain BatchNorm for one process and in evaluation.

    Not a subclass of ``nn.SyncBatchNorm``: DDP refuses those on the CPU. Its state dict is
    BatchNorm's, so a checkpoint loads into the plain network.
    """

    def _check_input_dim(self, input: torch.Tensor) -> None:  # noqa: A002 - torch's name
        if input.dim() < 2:
            raise ValueError(f"expected at least 2D input (got {input.dim()}D input)")

    def forward(self, input: torch.Tensor) -> torch.Tensor:  # noqa: A002 - torch's name
        if not (self.training and world_size() > 1):
            return super().forward(input)
        self._check_input_dim(input)
        factor = 0.0 if self.momentum is None else self.momentum
        if self.track_running_stats and self.num_batches_tracked is not None:
            self.num_batches_tracked.add_(1)
            if self.momentum is None:  # cumulative moving average
                factor = 1.0 / float(self.num_batches_tracked)
        track = self.track_running_stats
        return sync_batch_norm(input, self.weight, self.bias, self.running_mean if track else None,
                               self.running_var if track else None, factor, self.eps)


def convert_sync_batchnorm(module: nn.Module, device: torch.device) -> nn.Module:
    """Every BatchNorm layer of ``module`` synchronised over the processes, sharing its parameters
    and buffers (so optimisers keep working): torch's ``nn.SyncBatchNorm`` on CUDA,
    :class:`CPUSyncBatchNorm` on the CPU. Returns the converted module (``module`` itself unless it
    is a BatchNorm layer)."""
    if device.type != "cpu":
        return nn.SyncBatchNorm.convert_sync_batchnorm(module)
    out = module
    if isinstance(module, nn.modules.batchnorm._BatchNorm) and not isinstance(module, CPUSyncBatchNorm):
        out = CPUSyncBatchNorm(module.num_features, module.eps, module.momentum, module.affine,
                               module.track_running_stats)
        if module.affine:
            out.weight, out.bias = module.weight, module.bias
        out.running_mean, out.running_var = module.running_mean, module.running_var
        out.num_batches_tracked = module.num_batches_tracked
        out.train(module.training)
    for name, child in module.named_children():
        out.add_module(name, convert_sync_batchnorm(child, device))
    return out


def wrap(module: nn.Module, env: DistEnv, device: torch.device) -> nn.Module:
    """``module`` inside DistributedDataParallel for this process (its parameters are broadcast from
    rank 0); ``module`` itself for a single process."""
    if not env.distributed:
        return module
    ids = [device.index] if device.type == "cuda" else None
    return nn.parallel.DistributedDataParallel(module, device_ids=ids)

