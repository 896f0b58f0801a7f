#!/usr/bin/env bash
# Soak: ROBOTS robots stream to one release server in back-to-back rounds of ROUND
# seconds (every round opens a new session per robot, as robots that reconnect
# without resuming do) for DURATION seconds in all, and the server's resident memory,
# threads and open files are printed every 10 s. Sessions idle for IDLE_EVICT seconds
# leave memory (session.idle_evict_s), so memory must level off after warm-up.
# The verdict compares the end with the value at WARMUP seconds (goal: RSS within
# 10 %, threads constant but for tracking's per-frame ones).
#
# Usage: deploy/soak.sh <bin-dir>
# Environment: ROBOTS=8 DURATION=600 ROUND=30 RATE=5 (Hz per robot: what this 2-core
#   machine sustains for 8 robots with segmentation) IDLE_EVICT=10 WARMUP=120
#   MAX_PLACES=500 (fleet.max_places)
#   MODEL (../shared/models/yolov8n-seg_fp32_640.onnx; "none": no perception)
#   OUT (a temp dir: the samples as CSV, the server log, each round's report)
set -euo pipefail
BIN=${1:?usage: soak.sh <bin-dir>}
cd "$(dirname "$0")/.."
SHARED=${SHARED:-../shared}
TUM=${TUM:-$SHARED/data/tum/rgbd_dataset_freiburg1_rpy}
ROBOTS=${ROBOTS:-8}; DURATION=${DURATION:-600}; ROUND=${ROUND:-30}; RATE=${RATE:-5}
IDLE_EVICT=${IDLE_EVICT:-10}; WARMUP=${WARMUP:-120}; MAX_PLACES=${MAX_PLACES:-500}
MODEL=${MODEL:-$SHARED/models/yolov8n-seg_fp32_640.onnx}
OUT=${OUT:-$(mktemp -d)}
mkdir -p "$OUT"
free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
grpc="127.0.0.1:$(free_port)"; http="127.0.0.1:$(free_port)"
# The fleet's place index is bounded by fleet.max_places (5000 by default, about 60 KB
# a keyframe: 300 MB per fleet, reached after an hour of this load); the soak bounds it
# at MAX_PLACES so that it is full within the warm-up and what is left is the sessions.
printf '[session]\nidle_evict_s = %s\n[fleet]\nmax_places = %s\n' "$IDLE_EVICT" "$MAX_PLACES" >"$OUT/soak.toml"
model_args=(--model "$MODEL"); [ "$MODEL" = none ] && model_args=(--no-perception)
"$BIN/stillmap-server" --config "$OUT/soak.toml" --store "$OUT/soak.redb" "${model_args[@]}" --no-zenoh \
  --grpc-listen "$grpc" --http-listen "$http" >"$OUT/server.out" 2>"$OUT/server.log" &
server=$!
rounds=; trap 'kill $server 2>/dev/null || true; [ -n "$rounds" ] && kill $rounds 2>/dev/null || true' EXIT
for _ in $(seq 300); do
  grep -q "ready" "$OUT/server.out" 2>/dev/null && break
  kill -0 $server 2>/dev/null || { echo "soak: server failed to start:" >&2; cat "$OUT/server.log" >&2; exit 1; }
  sleep 0.1
done
echo "soak: $ROBOTS robots x $RATE Hz, a new session per robot every $ROUND s, for $DURATION s; $(nproc) cores; files in $OUT" >&2
(
  end=$((SECONDS + DURATION)); round=0
  while [ $SECONDS -lt $end ]; do
    round=$((round + 1))
    "$BIN/stillmap-client" fleet --robots "$ROBOTS" --source "tum:$TUM" --rate "$RATE" --duration "$ROUND" \
      --server "http://$grpc" --http "http://$http" --robot-prefix soak --summary-json "$OUT/round-$round.json" \
      >"$OUT/round-$round.md" 2>>"$OUT/client.log" || echo "soak: round $round failed (see $OUT/client.log)" >&2
  done
) &
rounds=$!
metric() { curl -s "http://$http/metrics" | awk -v m="$1" '$1 == m { print $2 }'; }
echo "t_s,rss_mb,threads,open_files,sessions_opened,resident,evicted,frames_processed" >"$OUT/samples.csv"
printf '| t s | RSS MB | threads | open files | sessions opened | in memory | evicted | frames processed |\n|---|---|---|---|---|---|---|---|\n'
start=$SECONDS
while kill -0 $rounds 2>/dev/null; do
  t=$((SECONDS - start))
  rss=$(awk '/^VmRSS/ { printf "%.0f", $2 / 1024 }' /proc/$server/status)
  threads=$(awk '/^Threads/ { print $2 }' /proc/$server/status)
  files=$(ls /proc/$server/fd | wc -l)
  opened=$(metric stillmap_sessions_total); resident=$(metric stillmap_sessions_resident)
  evicted=$(metric stillmap_sessions_evicted_total); processed=$(metric 'stillmap_frames_processed_total{transport="grpc"}')
  echo "$t,$rss,$threads,$files,${opened:-0},${resident:-0},${evicted:-0},${processed:-0}" >>"$OUT/samples.csv"
  echo "| $t | $rss | $threads | $files | ${opened:-0} | ${resident:-0} | ${evicted:-0} | ${processed:-0} |"
  sleep 10
done
wait $rounds || true
python3 - "$OUT/samples.csv" "$WARMUP" "$(nproc)" <<'PY'
import csv, sys
rows = [dict((k, float(v)) for k, v in r.items()) for r in csv.DictReader(open(sys.argv[1]))]
warm = float(sys.argv[2])
after = [r for r in rows if r["t_s"] >= warm]
if not after:
    sys.exit("soak: shorter than the warm-up; nothing to compare")
base, last = after[0], after[-1]
peak = max(r["rss_mb"] for r in after)
threads = [int(r["threads"]) for r in after]
# Each pipeline thread runs tracking's dense odometry on a scoped thread of its own
# for part of every frame: a sample sees between 0 and nproc of those.
cores = int(sys.argv[3])
growth = (last["rss_mb"] - base["rss_mb"]) / base["rss_mb"] * 100
print(f"\nRSS at {base['t_s']:.0f} s {base['rss_mb']:.0f} MB, at the end {last['rss_mb']:.0f} MB ({growth:+.1f} %), peak after warm-up {peak:.0f} MB; "
      f"threads after warm-up {min(threads)}..{max(threads)} (long-lived {min(threads)}, plus up to {cores} per-frame ones); "
      f"sessions opened {last['sessions_opened']:.0f}, in memory at the end {last['resident']:.0f}, evicted {last['evicted']:.0f}")
flat = abs(growth) <= 10 and max(threads) - min(threads) <= cores and threads[-1] - min(threads) <= cores
print("flat (RSS within 10 % of its warm-up value, threads constant but for the per-frame ones)" if flat else "NOT flat")
PY
