#!/usr/bin/env bash
# Part of benchmarks/gpu_generate.sh, which made docs/benchmarks.md, "Generator on fresh samples (GPU)" (issue 34, 04694f5).
#
# Extract out/gpu/carry and print the environment for it (benchmarks/gpu_generate.sh calls it).
# The carry: ../shared/tools/gpu-generate/build_carry.py --out out/gpu/carry --subjects DATASET, with its
# project.tar.xz deleted (the device gets the working tree itself). Run on the device from the repo root:
#
#     eval "$(bash benchmarks/gpu_extract.sh /tmp/gpu_work)"
#
# $1: work dir (default /tmp/gpu_work; emptied first). Knobs: GPU_CARRY (default out/gpu/carry in the
# repo), PY (default python3; used only where there is no xz binary).
# Result: $WORK/site (mitsuba, drjit, OpenImageIO, kornia, kornia_rs, fallback_lib),
# $WORK/premade/subjects (the 8 embedded-default subjects + index.json).
# Stdout: only `export ...` lines (PYTHONPATH=$WORK/site:<repo root>, PYTHONUNBUFFERED, and
# LD_LIBRARY_PATH / DRJIT_LIBOPTIX_PATH where needed, as gpu-generate/run_gpu.sh sets them). Messages: stderr.
set -euo pipefail
exec 3>&1 1>&2

HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
ROOT=$(cd "$HERE/.." && pwd)
CARRY=${GPU_CARRY:-$ROOT/out/gpu/carry}
WORK=${1:-/tmp/gpu_work}
PY=${PY:-python3}
mkdir -p "$WORK"
WORK=$(cd "$WORK" && pwd)
case "$WORK" in
/ | "$ROOT" | "$ROOT"/* | "${HOME:-/root}") echo "extract.sh: refusing to empty $WORK" && exit 2 ;;
esac

# ---- extract (as run_gpu.sh: tar -xJ, or Python's tarfile where there is no xz) -------------------
shopt -s nullglob
tars=("$CARRY"/*.tar.xz)
((${#tars[@]})) || { echo "extract.sh: no .tar.xz in $CARRY"; exit 2; }
rm -rf "$WORK" && mkdir -p "$WORK"
t0=$SECONDS
for f in "${tars[@]}"; do
    if command -v xz >/dev/null; then
        tar -C "$WORK" -xJf "$f"
    else
        "$PY" -c "import sys, tarfile; tarfile.open(sys.argv[1]).extractall(sys.argv[2], **({'filter': 'data'} if hasattr(tarfile, 'data_filter') else {}))" "$f" "$WORK"
    fi
done
echo "extract.sh: ${#tars[@]} tarballs from $CARRY into $WORK in $((SECONDS - t0))s"
du -sh "$WORK"/* | sed 's/^/  /'

# The pre-made subjects: subjects.tar.xz holds premade/subjects/ already; check it is complete.
n=$(ls "$WORK/premade/subjects"/anny_*.npz 2>/dev/null | wc -l)
[[ -f $WORK/premade/subjects/index.json ]] || { echo "extract.sh: $WORK/premade/subjects/index.json missing"; exit 2; }
echo "extract.sh: $n pre-made subjects in $WORK/premade/subjects"

# ---- environment (exactly as run_gpu.sh) -------------------------------------------------------
export PYTHONPATH="$WORK/site:$ROOT"
export PYTHONUNBUFFERED=1
# Byte-compile the carried packages once (worker start-up then does not compile kornia & co.).
timeout 60 "$PY" -m compileall -q -j 0 "$WORK/site" >/dev/null 2>&1 || echo "extract.sh: compileall failed (not needed)"
LDP0=${LD_LIBRARY_PATH:-}
if ! ldconfig -p 2>/dev/null | grep -q 'libatomic\.so\.1 '; then
    export LD_LIBRARY_PATH="$WORK/site/fallback_lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
    echo "extract.sh: libatomic.so.1 not known to ldconfig: using the carried copy"
fi
# Dr.Jit dlopens the driver's libcuda.so.1 and libnvoptix.so.1: where ldconfig does not know them, add the folder.
for lib in libcuda.so.1 libnvoptix.so.1; do
    ldconfig -p 2>/dev/null | grep -q "$lib " && continue
    for d in /usr/local/nvidia/lib64 /usr/local/nvidia/lib /usr/lib/x86_64-linux-gnu/nvidia /usr/lib64; do
        if [[ -e $d/$lib ]]; then
            [[ :${LD_LIBRARY_PATH:-}: == *":$d:"* ]] || export LD_LIBRARY_PATH="${LD_LIBRARY_PATH:+$LD_LIBRARY_PATH:}$d"
            [[ $lib == libnvoptix.so.1 ]] && export DRJIT_LIBOPTIX_PATH="$d/$lib"
            echo "extract.sh: $lib not known to ldconfig; found in $d (added to LD_LIBRARY_PATH)"
            break
        fi
    done
done

{
    printf 'export PYTHONPATH=%q\n' "$PYTHONPATH"
    printf 'export PYTHONUNBUFFERED=1\n'
    printf 'export GPU_WORK=%q\n' "$WORK"
    [[ ${LD_LIBRARY_PATH:-} != "$LDP0" ]] && printf 'export LD_LIBRARY_PATH=%q\n' "$LD_LIBRARY_PATH"
    [[ -n ${DRJIT_LIBOPTIX_PATH:-} ]] && printf 'export DRJIT_LIBOPTIX_PATH=%q\n' "$DRJIT_LIBOPTIX_PATH"
    true
} >&3
echo "extract.sh: PYTHONPATH=$PYTHONPATH LD_LIBRARY_PATH=${LD_LIBRARY_PATH:-} DRJIT_LIBOPTIX_PATH=${DRJIT_LIBOPTIX_PATH:-}"
