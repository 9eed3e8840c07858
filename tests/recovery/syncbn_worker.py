"""Run under torchrun by test_ddp.py (not a test module): each rank puts its rows of one seeded
batch through :class:`recovery.distributed.CPUSyncBatchNorm`; rank 0 saves every rank's outputs and
input gradients, the parameter gradients summed over the ranks and the running statistics to
``argv[1]``, for comparison with a plain BatchNorm on the whole batch."""

from __future__ import annotations

import sys

import torch

from recovery import distributed as D


def case(bn: torch.nn.Module, x: torch.Tensor, g: torch.Tensor, env: D.DistEnv) -> dict[str, torch.Tensor]:
    sbn = D.convert_sync_batchnorm(bn, torch.device("cpu"))
    part = x.shape[0] // env.world_size
    rows = slice(env.rank * part, (env.rank + 1) * part)
    xi = x[rows].clone().requires_grad_()
    y = sbn(xi)
    (y * g[rows]).sum().backward()  # the global loss is the sum of the ranks' sums
    return {"y": D.gather(y.detach()), "dx": D.gather(xi.grad), "dw": D.all_sum(sbn.weight.grad),
            "db": D.all_sum(sbn.bias.grad), "mean": sbn.running_mean.clone(), "var": sbn.running_var.clone(),
            "tracked": sbn.num_batches_tracked.clone(),
            "synchronised": torch.tensor(isinstance(sbn, D.CPUSyncBatchNorm))}


def inputs() -> list[tuple[str, torch.Tensor, torch.nn.Module, torch.Tensor]]:
    """``(name, batch, layer, upstream gradient)``: the same on every rank (seeded), float64."""
    gen = torch.Generator().manual_seed(0)
    x2 = torch.randn(8, 3, 5, 4, generator=gen, dtype=torch.float64) * 2.0 + 1.0
    x1 = torch.randn(6, 4, generator=gen, dtype=torch.float64) * 0.5 - 3.0
    cases = []
    for name, x, bn in (("2d", x2, torch.nn.BatchNorm2d(3, momentum=0.1)),
                        ("1d", x1, torch.nn.BatchNorm1d(4, momentum=None))):  # None: cumulative average
        bn = bn.double()
        with torch.no_grad():
            bn.weight.copy_(torch.rand(bn.num_features, generator=gen, dtype=torch.float64) + 0.5)
            bn.bias.copy_(torch.rand(bn.num_features, generator=gen, dtype=torch.float64) - 0.5)
        cases.append((name, x, bn, torch.randn(x.shape, generator=gen, dtype=torch.float64)))
    return cases


def main() -> None:
    env = D.from_environment()
    D.init(env, torch.device("cpu"))
    try:
        out = {name: case(bn, x, g, env) for name, x, bn, g in inputs()}
        if env.main:
            torch.save(out, sys.argv[1])
    finally:
        D.shutdown()


if __name__ == "__main__":
    main()
