"""Close placement's costs (issue 55, docs/close.md): the exact occupancy tests per query, and the
generator's images/s with ``people.placement: close`` against the defaults, on fresh samples.

    python benchmarks/bench_close.py --subjects out/close/subjects --out docs/benchmarks.md

1. **The exact tests** on one Anny body (13,348 vertices, 26,692 faces) of ``--subjects``: 100,000
   LEAP-style query points (:func:`blsm.occupancy.sample_points`), set-up and per-query time of
   libigl's exact winding number, its fast winding number, and :class:`blsm.occupancy.MeshSDF`
   (the placement's signed distance), and whether their inside answers agree.
2. **The generator**, 1 worker, warm kernel caches, interleaved rounds of three arms on fresh
   samples (each round its own part of each arm's dataset): the embedded defaults (1 person); the
   close config's people (2-3, ``poses.arms_rate`` 0.3, ``camera.fill`` [0.5, 0.85]) placed apart;
   the same placed close with contact labels (``configs/synth/close.yaml``). Each arm is
   ``benchmarks/bench_generate.py --workers 1 --no-cold --bare 0``; ratios are of the rounds' means.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from report import write_section

SEED = ["--set", "seed=55"]  # the close config's seed: its subjects serve every arm
PEOPLE = ["--set", "people.min=2", "--set", "people.max=3", "--set", "poses.arms_rate=0.3", "--set", "camera.fill=[0.5, 0.85]"]
ARMS = {
    "defaults (1 person)": SEED,
    "2-3 people apart": SEED + PEOPLE,
    "2-3 people close, contacts": SEED + PEOPLE + ["--set", "people.placement=close", "--set", "labels.contact_distance=0.02"],
}


def exact_tests(subjects: Path, n: int = 100_000) -> list[str]:
    from blsm import occupancy
    from synth.subjects import load_subject

    s = load_subject(sorted(subjects.glob("*.npz"))[0])
    v, f = s.vertices.astype(np.float64), s.faces
    q = occupancy.sample_points(v, f, n // 2, n - n // 2, np.random.default_rng(0))
    rows, answers = [], {}
    import igl

    fi = f.astype(np.int64)
    per_call = {  # set-up and query in one call each time
        "libigl exact winding number": lambda x: igl.winding_number(v, fi, x) > 0.5,
        "libigl fast winding number": lambda x: igl.fast_winding_number(v, fi, x) > 0.5,
    }
    for name, fn in per_call.items():
        t0 = time.perf_counter()
        fn(q[:10])
        fixed = time.perf_counter() - t0  # a call of 10 points: the call's set-up
        t0 = time.perf_counter()
        answers[name] = fn(q)
        total = time.perf_counter() - t0
        rows.append(f"| {name} | {1e3 * fixed:.1f} (every call) | {1e6 * (total - fixed) / n:.2f} |")
    t0 = time.perf_counter()
    sdf = occupancy.MeshSDF(v, f)
    fixed = time.perf_counter() - t0
    t0 = time.perf_counter()
    answers["MeshSDF"] = sdf(q)[0] < 0
    rows.append(f"| MeshSDF (AABB tree and pseudonormals; the placement's test) | {1e3 * fixed:.1f} (once a mesh) | "
                f"{1e6 * (time.perf_counter() - t0) / n:.2f} |")
    ref = answers[next(iter(answers))]
    agree = ", ".join(f"{k.split(' (')[0]} {int((a == ref).sum())}/{n}" for k, a in answers.items())
    return [f"One Anny body ({len(v)} vertices, {len(f)} faces), {n} query points (half within N(0, 1 cm^2) of the "
            "surface, half uniform in the box grown by 10 %), one process:", "",
            "| inside test | set-up (ms) | per query (us) |", "|---|---:|---:|", *rows, "",
            f"Inside answers equal to the exact winding number's: {agree}.", ""]


def generator(subjects: Path, rounds: int, images: int, seconds: float, work: Path) -> tuple[list[str], dict]:
    script = Path(__file__).with_name("bench_generate.py")
    rates: dict[str, list[float]] = {k: [] for k in ARMS}
    first: dict[str, list[float]] = {k: [] for k in ARMS}
    for r in range(rounds):
        for arm, sets in ARMS.items():
            out = work / f"{r}_{len(rates[arm])}_{abs(hash(arm)) % 10**6}.jsonl"
            cmd = [sys.executable, str(script), "--workers", "1", "--images", str(images), "--max-seconds", str(seconds),
                   "--warmup", "6", "--bare", "0", "--no-cold", "--subjects", str(subjects), "--part-offset", str(r),
                   "--json", str(out), *sets]  # fmt: skip
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
            rec = json.loads(out.read_text().splitlines()[0])
            rates[arm].append(rec["steady_img_per_s"])
            first[arm].append(rec["first_image_s"])
            print(f"[bench_close] round {r + 1} {arm}: {rec['steady_img_per_s']} img/s", flush=True)
    base = statistics.fmean(rates["defaults (1 person)"])
    apart = statistics.fmean(rates["2-3 people apart"])
    lines = ["| arm | steady img/s (rounds) | mean | ratio to the defaults | ratio to apart | first image (s) |",
             "|---|---:|---:|---:|---:|---:|"]
    for arm in ARMS:
        m = statistics.fmean(rates[arm])
        lines.append(f"| {arm} | {', '.join(f'{x:.3f}' for x in rates[arm])} | {m:.3f} | {m / base:.2f} | "
                     f"{m / apart:.2f} | {', '.join(f'{x:.1f}' for x in first[arm])} |")
    return lines, rates


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", type=Path, required=True, help="subjects/ made with seed 55 (out/close/subjects)")
    ap.add_argument("--out", type=Path, help="docs/benchmarks.md: write the section there")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--images", type=int, default=60)
    ap.add_argument("--max-seconds", type=float, default=90.0)
    ap.add_argument("--note", default="", help="a line on the machine's load, printed under the table")
    args = ap.parse_args()
    lines = exact_tests(args.subjects)
    print("\n".join(lines), flush=True)
    with tempfile.TemporaryDirectory(prefix="bench_close_") as tmp:
        gen, _ = generator(args.subjects, args.rounds, args.images, args.max_seconds, Path(tmp))
    date = time.strftime("%Y-%m-%d")
    lines += [f"The generator ({date}), 1 worker, warm kernel caches, {args.rounds} interleaved rounds, at most "
              f"{args.images} fresh images or {args.max_seconds:g} s a run (256 px, 36 spp, hair, shadows):", "", *gen]
    if args.note:
        lines += ["", args.note]
    print("\n".join(gen))
    if args.out:
        write_section(args.out, "close", "Close placement: exact tests and generator time (issue 55)",
                      "benchmarks/bench_close.py", lines,
                      command=f"`python benchmarks/bench_close.py --subjects out/close/subjects --rounds {args.rounds} "
                              f"--images {args.images} --max-seconds {args.max_seconds:g} --out docs/benchmarks.md`")
    return 0


if __name__ == "__main__":
    sys.exit(main())
