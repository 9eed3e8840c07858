"""Spiral mesh networks on the CPU: the Table 4.1 autoencoder's training throughput (forward and
backward, meshes/s), the spiral decoder against the BLSM forward pass at the same batch (meshes/s),
and SpiralConv's vertex-major gather against the batch-major reference (the same convolution);
written to the ``mesh`` section of ``docs/benchmarks.md``. Conditions alternate in rounds so that
machine load affects them alike.

    python benchmarks/bench_mesh.py --out docs/benchmarks.md
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).parent))

from report import write_section  # noqa: E402

import blsm  # noqa: E402
from blsm.spiral.conv import spiral_conv, spiral_gather  # noqa: E402
from recovery.mesh.operators import mesh_operators  # noqa: E402
from recovery.models.mesh_ae import MeshAutoencoder  # noqa: E402


def rate(fn, n: int, items: int, sync=lambda: None) -> float:
    sync()
    t = time.perf_counter()
    for _ in range(n):
        fn()
    sync()
    return items * n / (time.perf_counter() - t)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="docs/benchmarks.md")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--device", default="cpu", help="cpu (the make bench section) or cuda (a 'mesh_gpu' section)")
    args = ap.parse_args(argv)
    dev = torch.device(args.device)
    torch.set_num_threads(2)
    torch.manual_seed(0)
    body = blsm.load().to(dev)
    ops = mesh_operators()
    nv = body.num_vertices
    ae = MeshAutoencoder(ops, torch.zeros(nv, 3), torch.ones(nv, 3)).to(dev)
    opt = torch.optim.Adam(ae.parameters(), 1e-4)
    b = args.batch
    x = torch.randn(b, nv, 3, device=dev)
    z = torch.randn(b, 128, device=dev)
    pose = torch.randn(b, body.num_dofs, device=dev)
    bone = body.population_bone[:b].float()
    shape = body.population_shape[:b].float()
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)

    def train_step() -> None:
        loss = (ae(x) - x).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()

    def decode() -> None:
        with torch.no_grad():
            ae.decoder(z)

    def blsm_forward() -> None:
        with torch.no_grad():
            body(pose=pose, bone=bone, shape=shape)

    conv = ae.encoder.convs[0]  # level 0, 16 -> 16 channels, 2 rings
    feat = torch.randn(b, nv, 16, device=dev, requires_grad=True)
    feat_vm = feat.detach().transpose(0, 1).contiguous().requires_grad_(True)

    def conv_vertex_major() -> None:
        conv(feat_vm).sum().backward()

    def conv_batch_major() -> None:
        torch.nn.functional.linear(spiral_gather(feat, conv.indices), conv.linear.weight, conv.linear.bias).sum().backward()

    torch.testing.assert_close(spiral_conv(feat_vm, conv.indices, conv.linear.weight, conv.linear.bias).transpose(0, 1),
                               torch.nn.functional.linear(spiral_gather(feat, conv.indices), conv.linear.weight, conv.linear.bias),
                               rtol=1e-4, atol=1e-4)
    conds = {"ae": train_step, "decoder": decode, "blsm": blsm_forward, "vm": conv_vertex_major, "bm": conv_batch_major}
    for fn in conds.values():  # warm-up
        fn()
    res: dict[str, list[float]] = {k: [] for k in conds}
    for _ in range(args.rounds):
        for k, fn in conds.items():
            res[k].append(rate(fn, args.steps, b, sync))
    med = {k: sorted(v)[len(v) // 2] for k, v in res.items()}
    where = (f"GPU: {torch.cuda.get_device_name(dev)}" if dev.type == "cuda"
             else f"Machine: {platform.processor() or platform.machine()}, 2 threads")
    lines = [
        f"{where}, torch {torch.__version__}; batch {b}; "
        f"template {nv} vertices, levels {ops.sizes}; median of {args.rounds} rounds of {args.steps} calls.",
        "",
        "| | meshes / s | ratio |",
        "| --- | ---: | ---: |",
        f"| autoencoder (Table 4.1) training step: forward, L1, backward, Adam | {med['ae']:.1f} | |",
        f"| spiral decoder forward (latent -> {nv} vertices) | {med['decoder']:.1f} | **{med['decoder'] / med['blsm']:.2f}** of BLSM |",
        f"| BLSM forward (pose, bone, shape -> vertices) | {med['blsm']:.1f} | 1.00 |",
        f"| level-0 SpiralConv forward + backward, vertex-major (used) | {med['vm']:.1f} | **{med['vm'] / med['bm']:.2f}** of batch-major |",
        f"| the same, batch-major gather (reference) | {med['bm']:.1f} | 1.00 |",
    ]
    if dev.type == "cuda":
        write_section(Path(args.out), "mesh_gpu", "Spiral mesh networks (GPU)", "benchmarks/bench_mesh.py", lines,
                      command=f"`python benchmarks/bench_mesh.py --device cuda --batch {b} --steps {args.steps} "
                              f"--rounds {args.rounds}` on a lent GPU (not part of `make bench`, which needs none)")
    else:
        write_section(Path(args.out), "mesh", "Spiral mesh networks (CPU)", "benchmarks/bench_mesh.py", lines)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
