#!/usr/bin/env bash
# One GPU session (../shared/gpu_session.md, docs/gpu.md): fine-tune the shipped model on the generator's current
# version, ship the result as float16 parts, then time the one-line `predict` with it on rendered frames and a
# video. Everything it reports goes to $OUT. Run from the repository root with the node's Python:
#
#   OUT=/tmp/out COMMIT=abc1234 bash scripts/gpu_session.sh                   # one GPU, 16 cores
#   (COMMIT: the build machine's commit, for the log and the model card; EXTRA="--more fit --options" adds to the fit)
#   OUT=/tmp/out ACCEL=cpu SIZE=64 TRAIN=64 VAL=8 MAX_TIME=00:00:00:20 FRAMES=16 bash scripts/gpu_session.sh  # CPU check
#   OUT=/tmp/out PREDICT_ONLY=1 RUNS="video_bf16_b16_cl" bash scripts/gpu_session.sh  # no fit: time INIT's predict
#   (RUNS: the predict runs to time, by the names in part 2, which sets their order; default all)
set -uo pipefail
OUT=${OUT:?set OUT}; WORK=${WORK:-/tmp/gpu_session}; PY=${PY:-python3}
ACCEL=${ACCEL:-gpu}; PRECISION=${PRECISION:-bf16-mixed}; SIZE=${SIZE:-256}; TRAIN=${TRAIN:-4000}; VAL=${VAL:-300}
MAX_TIME=${MAX_TIME:-00:00:03:45}; SCHEDULE_S=${SCHEDULE_S:-210}; LR=${LR:-0.0005}; SEED=${SEED:-2}
CORES=$(nproc); FRAMES=${FRAMES:-400}; INIT=${INIT:-models/dapm-synthetic-r18-256}; NAME=${NAME:-dapm-synthetic-r18-256}
RUNS=${RUNS:-all}
NAMES=" eager_fp32_b4 bf16_b16_w8_cl video_eager_fp32_b4 compile_bf16_b16_w8_cl video_bf16_b16_cl "
for run in $RUNS; do  # NAMES: the runs of part 2, whose `both` lines they match; checked before the fit
  [ "$run" = all ] || [[ "$NAMES" == *" $run "* ]] || { echo "RUNS: no predict run '$run' (runs:$NAMES)" >&2; exit 2; }
done
mkdir -p "$OUT" "$WORK"
# the device's copy may carry an older .git than its files: COMMIT (the caller's `git rev-parse --short HEAD`)
# names the tree; without it `--dirty` at least says when the files differ from the commit named
TREE=${COMMIT:-$(git describe --always --dirty 2>/dev/null || echo '?')}
{ nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null || echo "no GPU"
  $PY -c "import sys, torch, lightning, timm, torchmetrics, cv2, albumentations; print('python', sys.version.split()[0],
'torch', torch.__version__, 'lightning', lightning.__version__, 'timm', timm.__version__, 'torchmetrics',
torchmetrics.__version__, 'opencv', cv2.__version__, 'albumentations', albumentations.__version__)"
  echo "cores $CORES, dapm-lightning at $TREE, $(date -u +%FT%TZ)"
} | tee "$OUT/fit.log"

# 1. fine-tune: the shipped model's weights, this generator's renders, a fresh warm-up and cosine over the time
if [ -n "${PREDICT_ONLY:-}" ]; then
  MODEL=$INIT
  echo "PREDICT_ONLY: no fit, predict with $MODEL" | tee -a "$OUT/fit.log"
else
  RUN=$WORK/run
  rm -rf "$RUN"  # a run left by an earlier call must not be shipped
  FIT=(fit --config dapm_lightning/configs/quickstart.yaml --model.init_weights "$INIT" --trainer.accelerator "$ACCEL"
       --trainer.precision "$PRECISION" --trainer.max_epochs -1 --trainer.max_time "$MAX_TIME"
       --trainer.default_root_dir "$RUN" --data.init_args.root "$WORK/data" --data.init_args.image_size "$SIZE"
       --data.init_args.train_size "$TRAIN" --data.init_args.val_size "$VAL" --data.init_args.render_seed "$SEED"
       --data.init_args.render_workers "$CORES" --data.init_args.num_workers $((CORES - 2))
       --model.optimizer.lr "$LR" --model.optimizer.schedule_seconds "$SCHEDULE_S" --trainer.enable_progress_bar false)
  read -ra MORE <<< "${EXTRA:-}"  # EXTRA: more fit options, split on spaces, no quotes (e.g. "--trainer.max_epochs 5")
  FIT+=("${MORE[@]}")
  COMMAND="dapm-lightning ${FIT[*]}"
  echo "$COMMAND" >> "$OUT/fit.log"
  $PY -m dapm_lightning "${FIT[@]}" 2>&1 | tail -40 >> "$OUT/fit.log"
  FIT_EXIT=${PIPESTATUS[0]}
  cp "$(find "$RUN" -name metrics.csv | head -1)" "$OUT/metrics.csv" 2>/dev/null
  LAST=$(find "$RUN" -name last.ckpt | head -1)
  echo "fit exit status $FIT_EXIT, last checkpoint: ${LAST:-none}" | tee -a "$OUT/fit.log"
  [ "$FIT_EXIT" = 0 ] && [ -n "$LAST" ] || exit 1
  $PY scripts/ship_model.py "$LAST" "$OUT/$NAME" --card <(echo "{\"command\": \"$COMMAND\", \"code\": \"$TREE\"}") \
    | tee -a "$OUT/fit.log"
  MODEL=$OUT/$NAME
fi

# 2. the one-line predict with it: 512x512 frames (a folder) and the same frames as a video, each run twice
# (all frames, then 50) so that the start-up (imports, loading, compiling) drops out of the images/s
$PY -m dapm_lightning synth --out "$WORK/frames" --train "$FRAMES" --val 1 --size 512 --seed 3 --workers "$CORES" \
  --quiet
$PY - "$WORK/frames/train/rgb" "$WORK/video.mp4" <<'PY'
import sys, pathlib, cv2
frames = sorted(pathlib.Path(sys.argv[1]).glob("*.png"))
video = cv2.VideoWriter(sys.argv[2], cv2.VideoWriter_fourcc(*"mp4v"), 30, (512, 512))
for path in frames:
    video.write(cv2.imread(str(path)))
video.release()
PY
ls "$WORK/frames/train/rgb" | head -50 | sed "s#^#$WORK/frames/train/rgb/#" > "$WORK/first50.txt"
DEADLINE=${DEADLINE:-100000}  # seconds since the start after which no predict run starts
timed() {  # NAME SOURCE [predict options]: one line of JSON per run in $OUT/predict.jsonl
  local name=$1 source=$2; shift 2
  [ $SECONDS -lt "$DEADLINE" ] || { echo "{\"run\": \"$name\", \"skipped\": \"deadline\"}" >> "$OUT/predict.jsonl"; return; }
  timeout 200 $PY - "$name" "$source" "$MODEL" "$WORK/p_$name" "$@" <<'PY' | tee -a "$OUT/predict.jsonl"
import json, resource, sys, time
import torch
from dapm_lightning.cli import main
name, source, model, out, *options = sys.argv[1:]
start = time.perf_counter()
try:
    main(["predict", source, "--ckpt_path", model, "--out", out, "--quiet", *options])
    code = 0
except SystemExit as stop:
    code = stop.code
seconds = time.perf_counter() - start
peak_gb = torch.cuda.max_memory_allocated() / 1e9 if torch.cuda.is_available() else None
rss_gb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss + resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss) / 1e6
print(json.dumps({"run": name, "options": options, "exit": code, "seconds": round(seconds, 2),
                  "gpu_peak_gb": peak_gb and round(peak_gb, 3), "host_rss_gb": round(rss_gb, 2)}), flush=True)
PY
}
FAST=(--precision bf16 --batch_size 16 --num_workers 8 --channels_last)
both() {  # NAME SOURCE [options]: all frames, then the first 50
  local name=$1 source=$2; shift 2
  [ "$RUNS" = all ] || [[ " $RUNS " == *" $name "* ]] || return 0
  timed "${name}_all" "$source" "$@"
  if [ "$source" = "$WORK/video.mp4" ]; then timed "${name}_first50" "$source" --max_frames 50 "$@"
  else timed "${name}_first50" "$WORK/first50.txt" "$@"; fi
}
both eager_fp32_b4 "$WORK/frames/train/rgb"
both bf16_b16_w8_cl "$WORK/frames/train/rgb" "${FAST[@]}"
both video_eager_fp32_b4 "$WORK/video.mp4"
both compile_bf16_b16_w8_cl "$WORK/frames/train/rgb" "${FAST[@]}" --compile
both video_bf16_b16_cl "$WORK/video.mp4" --precision bf16 --batch_size 16 --channels_last
echo "done in $SECONDS s"
