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
work=$(mktemp -d)
log=$work/server.log
# A store of its own, so every demo starts from an empty server.
"$BIN/stillmap-server" --store "$work/stillmap.redb" --model "${MODEL:-$SHARED/models/yolov8n-seg_fp32_640.onnx}" --grpc-listen "$GRPC" --http-listen "$HTTP" --zenoh-listen "$ZENOH" >"$log.out" 2>"$log" &
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
echo; echo "== server: the static semantic map of the gRPC session"
id=$(curl -fsS "http://$HTTP/api/v1/sessions" | python3 -c 'import json,sys; print([s["session_id"] for s in json.load(sys.stdin)["sessions"] if s["robot_id"]=="demo-grpc"][0])')
curl -fsS "http://$HTTP/api/v1/maps/$id" | python3 -c 'import json,sys; m=json.load(sys.stdin); print({k: m[k] for k in ["keyframes","occupied_voxels","blocks","memory_bytes","up_source","committed_keyframes"]})'
curl -fsS "http://$HTTP/api/v1/maps/$id/objects" | python3 -c 'import json,sys; o=json.load(sys.stdin)["objects"]; print("objects:", ", ".join("%s (%d voxels)" % (x["class_name"], x["voxels"]) for x in o[:8]))'
curl -fsS -o "$work/map.ply" "http://$HTTP/api/v1/maps/$id/cloud.ply"
curl -fsS -o "$work/occupancy.pgm" "http://$HTTP/api/v1/maps/$id/occupancy.pgm"
echo "saved $work/map.ply ($(stat -c %s "$work/map.ply") bytes) and $work/occupancy.pgm"
echo; echo "== server: the default fleet (the Zenoh robot saw the same room: place recognition merged it into the gRPC robot's frame)"
for _ in $(seq 300); do
  curl -fsS "http://$HTTP/api/v1/fleets" | python3 -c 'import json,sys; sys.exit(0 if json.load(sys.stdin)["place_recognition_backlog"] == 0 else 1)' && break
  sleep 0.1
done
curl -fsS "http://$HTTP/api/v1/fleets/default" | python3 <(cat <<'PY'
import json, sys
fleet = json.load(sys.stdin)
for m in fleet["sessions"]:
    frame = m["fleet_from_session"]
    if frame is None:
        how = "not merged"
    elif frame["anchor"]:
        how = "anchors the fleet's frame"
    else:
        how = "merged %.1f s into its keyframes (%d agreeing), fleet_from_session translation %s" % (frame["merged_after_s"], frame["support"], [round(v, 3) for v in frame["translation"]])
    print("%-12s %-28s %s" % (m["robot_id"], m["session_id"], how))
PY
)
echo "dashboard: http://$HTTP/ (while the server runs; STILLMAP_DEMO_KEEP=1 keeps it running)"
if [ -n "${STILLMAP_DEMO_KEEP:-}" ]; then
  echo "press Ctrl-C to stop the server"
  wait $server
fi
