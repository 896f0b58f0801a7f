#!/usr/bin/env bash
# The main job end to end: start the server with its embedded defaults, stream the
# real TUM clip over gRPC and then over Zenoh, print both summaries and the
# server's view of the sessions, then stop the server.
# Usage: deploy/demo.sh <bin-dir> [extra client args...]
set -euo pipefail
BIN=${1:?usage: demo.sh <bin-dir>}; shift || true
TUM=${TUM:-../shared/data/tum/rgbd_dataset_freiburg1_rpy}
GRPC=${STILLMAP_DEMO_GRPC:-127.0.0.1:50051}
HTTP=${STILLMAP_DEMO_HTTP:-127.0.0.1:8080}
ZENOH=${STILLMAP_DEMO_ZENOH:-tcp/127.0.0.1:7447}
RATE=${STILLMAP_DEMO_RATE:-realtime}

[ -d "$TUM" ] || { echo "demo: TUM clip not found at $TUM (set TUM=...)" >&2; exit 1; }
log=$(mktemp -d)/server.log
"$BIN/stillmap-server" --model "${MODEL:-$SHARED/models/yolov8n-seg_fp32_640.onnx}" --grpc-listen "$GRPC" --http-listen "$HTTP" --zenoh-listen "$ZENOH" >"$log.out" 2>"$log" &
server=$!
trap 'kill $server 2>/dev/null; wait $server 2>/dev/null || true' EXIT
for _ in $(seq 100); do
  grep -q "ready" "$log.out" 2>/dev/null && break
  kill -0 $server 2>/dev/null || { echo "demo: server failed to start:" >&2; cat "$log" >&2; exit 1; }
  sleep 0.1
done
cat "$log.out"

echo; echo "== gRPC: streaming $(basename "$TUM") at rate $RATE"
"$BIN/stillmap-client" stream --source "tum:$TUM" --transport grpc --server "http://$GRPC" \
  --robot-id demo-grpc --rate "$RATE" "$@"
echo; echo "== Zenoh: streaming $(basename "$TUM") at rate $RATE"
"$BIN/stillmap-client" stream --source "tum:$TUM" --transport zenoh --zenoh-connect "$ZENOH" \
  --robot-id demo-zenoh --rate "$RATE" "$@"
echo; echo "== server: GET /api/v1/sessions"
curl -fsS "http://$HTTP/api/v1/sessions"; echo
echo; echo "== server: frame counters from /metrics"
curl -fsS "http://$HTTP/metrics" | grep -E '^stillmap_(frames|bytes)_' || true
