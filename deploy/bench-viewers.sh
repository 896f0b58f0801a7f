#!/usr/bin/env bash
# Dashboard viewers against ingest (issue 21): one robot streams a TUM recording
# (`stillmap-client fleet --robots 1`, a ping-pong loop at the camera's rate) to a
# fresh server, alone and with VIEWERS dashboard event streams open (deploy/viewers.py,
# its own process at nice 19, as browsers elsewhere would be); RUNS pairs; prints one
# Markdown row per run and the means. The same measure as the ignored test
# `viewers_do_not_slow_a_streaming_robot`, for a machine without cargo.
#
# Usage: deploy/bench-viewers.sh <bin-dir>
# Environment: VIEWERS=500 RUNS=3 DURATION=15 (seconds per run) RATE=30 (Hz)
#   MODEL (../shared/models/yolov8n-seg_fp32_640.onnx)  TUM (../shared/data/tum/rgbd_dataset_freiburg1_rpy)
#   GPU=1  segmentation on CUDA (as deploy/bench-fleet.sh's GPU=1)   OUT (a temp dir)
set -euo pipefail
BIN=${1:?usage: bench-viewers.sh <bin-dir>}
cd "$(dirname "$0")/.."
SHARED=${SHARED:-../shared}
TUM=${TUM:-$SHARED/data/tum/rgbd_dataset_freiburg1_rpy}
MODEL=${MODEL:-$SHARED/models/yolov8n-seg_fp32_640.onnx}
VIEWERS=${VIEWERS:-500}; RUNS=${RUNS:-3}; DURATION=${DURATION:-15}; RATE=${RATE:-30}
OUT=${OUT:-$(mktemp -d)}
mkdir -p "$OUT"
[ -f "$MODEL" ] || { echo "bench-viewers: model $MODEL not found" >&2; exit 1; }

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }

echo "viewer benchmark: $(nproc) cores, ${GPU:+GPU, }$DURATION s per run at $RATE Hz, reports in $OUT" >&2
echo "| run | viewers | robot frames/s | latency p50 / p95 ms | /healthz | viewers still reading |"
echo "|---|---|---|---|---|---|"
fps_file="$OUT/fps.txt"; : >"$fps_file"
for run in $(seq "$RUNS"); do
  for n in 0 "$VIEWERS"; do
    tag="$OUT/run$run-v$n"
    grpc="127.0.0.1:$(free_port)"; http="127.0.0.1:$(free_port)"
    {
      echo "[limits]"
      echo "http_requests_per_minute = 0"
      echo "[http]"
      echo "max_event_viewers = $((VIEWERS + 16))"
      if [ -n "${GPU:-}" ]; then
        echo "[perception.segmentation]"
        echo 'execution_provider = "cuda"'
        echo "intra_threads = 1"
      fi
    } >"$tag.toml"
    "$BIN/stillmap-server" --config "$tag.toml" --store "$tag.redb" --model "$MODEL" --no-zenoh \
      --grpc-listen "$grpc" --http-listen "$http" >"$tag.server.out" 2>"$tag.server.log" &
    server=$!
    for _ in $(seq 600); do
      grep -q "ready" "$tag.server.out" 2>/dev/null && break
      kill -0 $server 2>/dev/null || { echo "bench-viewers: server failed to start:" >&2; cat "$tag.server.log" >&2; exit 1; }
      sleep 0.1
    done
    viewers_pid=
    if [ "$n" -gt 0 ]; then
      coproc VIEWERS_PROC { exec nice -n 19 python3 deploy/viewers.py 127.0.0.1 "${http#*:}" "$n"; }
      viewers_pid=$VIEWERS_PROC_PID
      read -r -t 120 line <&"${VIEWERS_PROC[0]}" || line=
      [ "$line" = ready ] || { echo "bench-viewers: the viewers did not all connect" >&2; kill $server; exit 1; }
    fi
    "$BIN/stillmap-client" fleet --robots 1 --source "tum:$TUM" --rate "$RATE" --duration "$DURATION" \
      --server "http://$grpc" --http "http://$http" --robot-prefix "viewers" --summary-json "$tag.json" >"$tag.table.md" || true
    health=$(python3 -c 'import sys, urllib.request, urllib.error
try: print(urllib.request.urlopen(sys.argv[1], timeout=10).status)
except urllib.error.HTTPError as e: print(e.code)
except Exception: print("down")' "http://$http/healthz")
    reading=0
    if [ -n "$viewers_pid" ]; then
      kill -0 "$viewers_pid" 2>/dev/null && reading=$n
      kill "$viewers_pid" 2>/dev/null; wait "$viewers_pid" 2>/dev/null || true
    fi
    kill $server 2>/dev/null; wait $server 2>/dev/null || true
    rm -f "$tag.redb"
    python3 - "$tag.json" "$run" "$n" "$health" "$reading" "$fps_file" <<'PY'
import json, sys
path, run, n, health, reading, fps_file = sys.argv[1:]
t = json.load(open(path))["total"]
fps = t["frames_per_second_per_robot"]
open(fps_file, "a").write(f"{n} {fps}\n")
print(f"| {run} | {n} | {fps:.2f} | {t['latency_ms_p50']:.0f} / {t['latency_ms_p95']:.0f} | {health} | {reading} |")
PY
  done
done
python3 - "$fps_file" "$VIEWERS" <<'PY'
import sys
rows = [line.split() for line in open(sys.argv[1])]
mean = lambda v: (lambda f: sum(f) / len(f))([float(r[1]) for r in rows if r[0] == v])
alone, watched = mean("0"), mean(sys.argv[2])
print(f"\nmean frames/s: {alone:.2f} alone, {watched:.2f} with {sys.argv[2]} viewers ({100 * (watched / alone - 1):+.1f} %)")
PY
