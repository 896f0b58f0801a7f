#!/usr/bin/env bash
# Fleet capacity: for each model, rate and robot count, start a fresh server (its
# own store, real segmentation model), run `stillmap-client fleet` against it, and
# print one Markdown row per run (the README's fleet table).
#
# Usage: deploy/bench-fleet.sh <bin-dir>
# Environment (defaults are this 2-core machine's sweep; GPU=1 the GPU server's):
#   ROBOTS="1 2 3 4"  RATES="10 15 30"  MODELS="320 640"  DURATION=20 (seconds per run)
#   GPU=1             segmentation on CUDA with the batching models from
#                     deploy/make-batched-model.py, ROBOTS="1 4 8 16 32", RATES=30
#   MODEL_DIR         where yolov8n-seg_fp32_<size>[_batch].onnx are (../shared/models;
#                     .deps/models for the batching ones)
#   OUT               folder for the per-run JSON reports, /metrics and server logs (a temp dir)
#   OPENCV_THREADS, PIPELINE_THREADS, SEG_NICE  session.opencv_threads /
#                     pipeline_threads, perception.segmentation.worker_nice
#                     (default: the server's defaults, 1 and one per core)
set -euo pipefail
BIN=${1:?usage: bench-fleet.sh <bin-dir>}
cd "$(dirname "$0")/.."
SHARED=${SHARED:-../shared}
TUM=${TUM:-$SHARED/data/tum/rgbd_dataset_freiburg1_rpy}
GPU=${GPU:-}
if [ -n "$GPU" ]; then
  ROBOTS=${ROBOTS:-"1 4 8 16 32"}; RATES=${RATES:-30}; MODELS=${MODELS:-"640"}
  MODEL_DIR=${MODEL_DIR:-.deps/models}; SUFFIX=_batch
else
  ROBOTS=${ROBOTS:-"1 2 3 4"}; RATES=${RATES:-"10 15 30"}; MODELS=${MODELS:-"320 640"}
  MODEL_DIR=${MODEL_DIR:-$SHARED/models}; SUFFIX=
fi
DURATION=${DURATION:-20}
OUT=${OUT:-$(mktemp -d)}
mkdir -p "$OUT"

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }

echo "fleet benchmark: $(nproc) cores, ${GPU:+GPU, }$DURATION s per run, reports in $OUT" >&2
echo "| model | robots | rate Hz | frames/s per robot | answered | dropped | p50 / p95 ms | mask age p50 / p95 | refused |"
echo "|---|---|---|---|---|---|---|---|---|"
for model in $MODELS; do
  file="$MODEL_DIR/yolov8n-seg_fp32_${model}${SUFFIX}.onnx"
  [ -f "$file" ] || { echo "bench-fleet: model $file not found" >&2; exit 1; }
  for rate in $RATES; do
    for n in $ROBOTS; do
      run="$OUT/m${model}-r${rate}-n${n}"
      grpc="127.0.0.1:$(free_port)"; http="127.0.0.1:$(free_port)"; zenoh="tcp/127.0.0.1:$(free_port)"
      config="$run.toml"
      {
        echo "[session]"
        echo "max_connected = 0"
        [ -n "${OPENCV_THREADS:-}" ] && echo "opencv_threads = $OPENCV_THREADS"
        [ -n "${PIPELINE_THREADS:-}" ] && echo "pipeline_threads = $PIPELINE_THREADS"
        echo "[perception.segmentation]"
        [ -n "${SEG_NICE:-}" ] && echo "worker_nice = $SEG_NICE"
        if [ -n "$GPU" ]; then
          echo 'execution_provider = "cuda"'
          echo "max_batch = ${MAX_BATCH:-16}"
          echo "max_queue_delay_ms = ${MAX_QUEUE_DELAY_MS:-4}"
          echo "workers = ${SEG_WORKERS:-2}"
          echo "intra_threads = 1"
        fi
      } >"$config"
      "$BIN/stillmap-server" --config "$config" --store "$run.redb" --model "$file" \
        --grpc-listen "$grpc" --http-listen "$http" --zenoh-listen "$zenoh" >"$run.server.out" 2>"$run.server.log" &
      server=$!
      for _ in $(seq 300); do
        grep -q "ready" "$run.server.out" 2>/dev/null && break
        kill -0 $server 2>/dev/null || { echo "bench-fleet: server failed to start:" >&2; cat "$run.server.log" >&2; exit 1; }
        sleep 0.1
      done
      "$BIN/stillmap-client" fleet --robots "$n" --source "tum:$TUM" --rate "$rate" --duration "$DURATION" \
        --server "http://$grpc" --zenoh-connect "$zenoh" --http "http://$http" --robot-prefix "m$model" \
        --summary-json "$run.json" >"$run.table.md" || true
      # The server's own counters (segmentation batch sizes and times, masks by source).
      python3 -c 'import sys, urllib.request; open(sys.argv[2], "wb").write(urllib.request.urlopen(sys.argv[1], timeout=10).read())' \
        "http://$http/metrics" "$run.metrics" || echo "bench-fleet: no /metrics for $run" >&2
      kill $server 2>/dev/null; wait $server 2>/dev/null || true
      rm -f "$run.redb"
      python3 - "$run.json" "$model" "$n" "$rate" <<'PY'
import json, sys
path, model, n, rate = sys.argv[1:]
r = json.load(open(path))
t = r["total"]
print(f"| {model} | {n} | {rate} | {t['frames_per_second_per_robot']:.1f} | {t['frames_answered']} | {t['frames_dropped']} "
      f"| {t['latency_ms_p50']:.0f} / {t['latency_ms_p95']:.0f} | {t['mask_age_p50']:.0f} / {t['mask_age_p95']:.0f} | {t['robots_failed']} |")
PY
    done
  done
done
