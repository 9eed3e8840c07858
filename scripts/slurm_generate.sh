#!/usr/bin/env bash
# Generate one dataset with a Slurm job array: task I of N makes part I/N of the shards into one
# folder on storage every node sees; a dependent job joins the parts (docs/scaling.md).
#
#   sbatch --array=1-16 scripts/slurm_generate.sh configs/synth/train_hdri.yaml /shared/data/train_hdri
#   sbatch --dependency=afterok:<array job id> --wrap "synth merge /shared/data/train_hdri"
#
# A task that fails or is pre-empted is simply re-submitted with the same index: --resume keeps the
# shards it finished (checked by SHA-256) and makes the rest, the same bytes. Parts never write the
# same file; the first one to arrive makes the dataset's subjects while the others wait for them.
#SBATCH --job-name=synth
#SBATCH --cpus-per-task=4
#SBATCH --mem=8G
#SBATCH --time=12:00:00
#SBATCH --output=synth-%A_%a.log
set -euo pipefail
CONFIG="${1:?usage: sbatch --array=1-N scripts/slurm_generate.sh CONFIG OUT_DIR}"
OUT="${2:?usage: sbatch --array=1-N scripts/slurm_generate.sh CONFIG OUT_DIR}"
I="${SLURM_ARRAY_TASK_ID:?not in a Slurm job array (sbatch --array=1-N)}"
N="${SLURM_ARRAY_TASK_COUNT:?not in a Slurm job array (sbatch --array=1-N)}"
# One worker process per two CPUs: each renders with Dr.Jit on the cores it is given.
WORKERS=$(( ${SLURM_CPUS_PER_TASK:-2} / 2 > 0 ? ${SLURM_CPUS_PER_TASK:-2} / 2 : 1 ))
exec synth generate "$CONFIG" --out "$OUT" --part "$I/$N" --workers "$WORKERS" --resume
