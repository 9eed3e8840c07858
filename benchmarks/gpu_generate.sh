#!/usr/bin/env bash
# Made docs/benchmarks.md, "Generator on fresh samples (GPU)" (issue 34, 2026-11-26, 41711a4 and 04694f5).
#
# The generator with Mitsuba's cuda_ad_rgb on a lent GPU machine (issue 34), in one call:
#
#     bash benchmarks/gpu_generate.sh          # from the repo root, on the GPU machine
#
# Needs out/gpu/carry (carried with the call: `carry: ["out/gpu/carry"]`): the trimmed Mitsuba, Dr.Jit,
# OpenImageIO, kornia and the pre-made subjects made by ../shared/tools/gpu-generate/build_carry.py, its
# project.tar.xz deleted (the call carries the working tree itself); benchmarks/gpu_extract.sh unpacks it. Steps, each under a timeout:
#   1. `synth generate -` (embedded defaults, cuda_ad_rgb, 8 workers, cold kernel cache), validated,
#      a contact sheet ($OUT/preview.png);
#      (GPU_CLI=0 skips it);
#   2. benchmarks/bench_generate.py: fresh samples per run, cold then warm kernel caches, 4/8/16
#      workers, the bare render beside them; nvidia-smi sampled every 0.5 s ($OUT/smi.csv).
# Results in $OUT (default /tmp/gpu_out): log.txt, gen.jsonl, benchmarks.md (the section), smi.csv.
set -u
OUT=${OUT:-/tmp/gpu_out}
WORKERS=${GPU_WORKERS:-"4 8 16"}
RUN_S=${GPU_RUN_S:-20}
mkdir -p "$OUT"
exec > >(tee "$OUT/log.txt") 2>&1
t0=$SECONDS
eval "$(bash benchmarks/gpu_extract.sh /tmp/gpu_work)" || exit 3
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
echo "cpus $(nproc); $(python3 -V)"
SUBJ=$GPU_WORK/premade/subjects

if [[ ${GPU_CLI:-1} == 1 ]]; then
echo "=== 1. synth generate (cold kernel cache, 8 workers) t=$((SECONDS - t0))s ==="
D=/tmp/gpu_cli
rm -rf "$D" /tmp/home_cli && mkdir -p "$D" /tmp/home_cli && cp -r "$SUBJ" "$D/"
s=$SECONDS
HOME=/tmp/home_cli timeout 150 python3 -m synth.cli generate - --out "$D" --num "${GPU_CLI_NUM:-48}" --workers "${GPU_CLI_WORKERS:-8}" \
    --set render.variant=cuda_ad_rgb
echo "cli generate rc=$? in $((SECONDS - s)) s (${GPU_CLI_NUM:-48} images, start-up and compiles included)"
timeout "${GPU_VALIDATE_S:-90}" python3 -m synth.cli validate "$D"
echo "validate rc=$?"
timeout 40 python3 -m synth.cli preview "$D" --out "$OUT/preview.png" --count 16 || true
fi

echo "=== 2. bench_generate t=$((SECONDS - t0))s ==="
nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv,noheader -lms 500 >"$OUT/smi.csv" &
smi=$!
# shellcheck disable=SC2086
timeout "${GPU_BENCH_S:-330}" python3 benchmarks/bench_generate.py --variant cuda_ad_rgb --subjects "$SUBJ" \
    --workers $WORKERS --images 2400 --max-seconds "$RUN_S" --warmup 48 --bare "${GPU_BARE:-32}" ${GPU_BENCH_ARGS:-} \
    --json "$OUT/gen.jsonl" --out "$OUT/benchmarks.md"
echo "bench rc=$?"
kill "$smi" 2>/dev/null
echo "done in $((SECONDS - t0)) s"
