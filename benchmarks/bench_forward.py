"""BLSM forward time on CPU against smplx's ``lbs()`` at the same V and J (``make bench``).

smplx's ``lbs`` is called on random tensors of the same size as the packaged BLSM: V vertices, J
joints, as many shape directions as BLSM has bone + shape coefficients, and the pose-corrective
blendshapes ((J - 1) * 9 directions) that ``lbs`` always applies; no SMPL model file is needed.
BLSM's forward includes Eq. 6, the bone-scale chain, correctives, shape basis, LBS and keypoints.
Both run in one process, interleaved, single-threaded and multi-threaded as torch is configured.
"""

from __future__ import annotations

import argparse
import datetime
import platform
import statistics
import time
from pathlib import Path

import torch
from report import write_section  # benchmarks/report.py (run as a script)


def _time(fn, reps: int) -> float:
    for _ in range(3):
        fn()
    samples = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t0)
    return statistics.median(samples)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help="write the markdown table here")
    parser.add_argument("--reps", type=int, default=30)
    args = parser.parse_args()

    import smplx.lbs

    import blsm

    model = blsm.load()
    v, j = model.num_vertices, model.num_joints
    nb = model.num_bone_coeffs + model.num_shape_coeffs
    g = torch.Generator().manual_seed(0)
    parents = torch.tensor(model.parents)
    template = model.template.clone()
    shapedirs = torch.randn(v, 3, nb, generator=g) * 1e-2
    posedirs = torch.randn((j - 1) * 9, v * 3, generator=g) * 1e-3
    j_reg = torch.rand(j, v, generator=g)
    j_reg /= j_reg.sum(1, keepdim=True)
    weights = model.weights.clone()

    rows = []
    for batch in (1, 32):
        x = torch.randn(batch, 47, generator=g)
        cb = torch.randn(batch, model.num_bone_coeffs, generator=g)
        cs = torch.randn(batch, model.num_shape_coeffs, generator=g)
        r = torch.randn(batch, 3, generator=g) * 0.3
        betas = torch.randn(batch, nb, generator=g)
        pose = torch.randn(batch, j * 3, generator=g) * 0.3

        def run_blsm():
            with torch.no_grad():
                model(pose=x, bone=cb, shape=cs, global_orient=r)

        def run_smplx():
            with torch.no_grad():
                smplx.lbs.lbs(betas, pose, template, shapedirs, posedirs, j_reg, parents, weights)

        tb, ts = [], []
        for _ in range(3):  # interleave to share machine noise
            tb.append(_time(run_blsm, args.reps))
            ts.append(_time(run_smplx, args.reps))
        tb_m, ts_m = min(tb), min(ts)
        rows.append((batch, tb_m * 1e3, ts_m * 1e3, tb_m / ts_m))
        print(f"batch {batch:3d}: BLSM {tb_m * 1e3:8.2f} ms   smplx.lbs {ts_m * 1e3:8.2f} ms   "
              f"ratio BLSM/smplx {tb_m / ts_m:.2f}")

    if args.out is not None:
        lines = [
            f"Measured {datetime.date.today().isoformat()} on {platform.machine()}, "
            f"{torch.get_num_threads()} torch threads, torch {torch.__version__}, "
            f"V = {v}, J = {j}, {nb} shape directions; median of {args.reps} calls, best of 3 "
            "interleaved rounds, `torch.no_grad()`.",
            "",
            "| batch | BLSM forward (ms) | smplx `lbs` (ms) | ratio BLSM / smplx |",
            "| ---: | ---: | ---: | ---: |",
        ]
        lines += [f"| {b} | {tb:.2f} | {ts:.2f} | {ratio:.2f} |" for b, tb, ts, ratio in rows]
        lines += [
            "",
            "smplx's `lbs` also applies (J - 1) * 9 pose-corrective blendshapes, which BLSM does not "
            "have; BLSM additionally evaluates Eq. 6, the bone-scale chain (Eqs. 4, 5), the "
            "bone-corrective blendshapes (Eq. 7) and the keypoints. Same V, J and number of shape "
            "directions; random inputs.",
            "",
        ]
        write_section(args.out, "forward", "BLSM forward vs smplx `lbs()` (CPU)", "benchmarks/bench_forward.py", lines)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
