#!/bin/bash
# Render a large synthetic UAPD-format data set as a SLURM array job: task K of N renders shard K/N
# (a contiguous part of the image list); together the shards are byte-identical to one run of
# `dapm-lightning synth` with the same settings (docs/synthetic.md). Submit from the repository root:
#
#   mkdir -p logs && sbatch scripts/synth_slurm.sh                      # 16 tasks, the settings below
#   OUT=/scratch/synth TRAIN=200000 sbatch --array=0-63 scripts/synth_slurm.sh
#
# The array must start at 0 and have no gaps (N = SLURM_ARRAY_TASK_COUNT). Render into an empty
# folder, or one holding a run with the same settings (a shard refuses a folder rendered otherwise).
# Afterwards check the set, e.g. with a dependent job:
#   sbatch --dependency=afterok:<JOBID> --wrap ".venv/bin/dapm-lightning doctor $OUT"
#
#SBATCH --job-name=dapm-synth
#SBATCH --array=0-15
#SBATCH --cpus-per-task=8
#SBATCH --mem=8G
#SBATCH --time=04:00:00
#SBATCH --output=logs/synth_%A_%a.out
set -euo pipefail

OUT=${OUT:-data/synth_large}
TRAIN=${TRAIN:-50000}
VAL=${VAL:-2000}
SIZE=${SIZE:-512}
SEED=${SEED:-0}
FAMILIES=${FAMILIES:-downtown=1,suburb=1,industrial=1,farmland=1,forest=1,water=1}
PYTHON=${PYTHON:-.venv/bin/python}

TASK=${SLURM_ARRAY_TASK_ID:?run this under sbatch --array=0-(N-1)}
COUNT=${SLURM_ARRAY_TASK_COUNT:?run this under sbatch --array=0-(N-1)}
FIRST=${SLURM_ARRAY_TASK_MIN:-0}
if [ "$FIRST" != 0 ]; then
  echo "the array must start at 0 (got --array starting at $FIRST)" >&2
  exit 2
fi

exec "$PYTHON" -m dapm_lightning.tools.synth --out "$OUT" --train "$TRAIN" --val "$VAL" --size "$SIZE" \
  --seed "$SEED" --families "$FAMILIES" --shard "$TASK/$COUNT" --workers "${SLURM_CPUS_PER_TASK:-1}"
