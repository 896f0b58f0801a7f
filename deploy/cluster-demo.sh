#!/usr/bin/env bash
# Several servers on one Zenoh network, on this machine (issue 22): a router
# (stillmap-router), two servers sharing a PostgreSQL (store.replica_url) and four
# robots streaming the public clip through the router. Prints the placement, the
# servers' view, a kill -9 of one server and where its robots went, each robot's
# frames and session (the dead server's robots resume theirs on the other), the
# replication cost per commit, and the latency through the router against a direct
# gRPC stream. Usage: deploy/cluster-demo.sh <bin-dir>
#   TUM (the clip), MODEL (segmentation; default none: --no-perception, so four
#   robots at 30 Hz fit a 2-core machine), CLUSTER_BASE_PORT (default 17400).
#   PostgreSQL's server programs: Debian's postgresql package (make deps).
set -euo pipefail
BIN=${1:?usage: cluster-demo.sh <bin-dir>}
TUM=${TUM:-../shared/data/tum/rgbd_dataset_freiburg1_rpy}
BASE=${CLUSTER_BASE_PORT:-17400}
ROUTER=tcp/127.0.0.1:$BASE
[ -d "$TUM" ] || { echo "cluster-demo: TUM clip not found at $TUM (set TUM=...)" >&2; exit 1; }
work=$(mktemp -d)
pids=()
PGBIN=$(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V | tail -1)
[ -x "$PGBIN/initdb" ] || { echo "cluster-demo: PostgreSQL's server programs not found (make deps installs Debian's postgresql)" >&2; exit 1; }
as_pg() { if [ "$(id -u)" = 0 ]; then runuser -u postgres -- "$@"; else "$@"; fi; } # PostgreSQL refuses to run as root
PGPORT=$((BASE + 40))
cleanup() {
  for p in "${pids[@]}"; do kill -9 "$p" 2>/dev/null || true; done; wait 2>/dev/null || true
  [ -d "$work/pg/data" ] && as_pg "$PGBIN/pg_ctl" -D "$work/pg/data" -m fast stop >/dev/null 2>&1 || true
  rm -rf "$work"
}
trap cleanup EXIT
perception=(--no-perception); [ -n "${MODEL:-}" ] && perception=(--model "$MODEL")

wait_for() { # file pattern what
  for _ in $(seq 300); do grep -q "$2" "$1" 2>/dev/null && return 0; sleep 0.1; done
  echo "cluster-demo: $3 did not start:" >&2; cat "$1" "$1.err" >&2 2>/dev/null; exit 1
}
json() { python3 -c "import json,sys; d=json.load(sys.stdin); print($1)"; }

# The storage the servers share: a fresh PostgreSQL cluster on loopback.
mkdir -p "$work/pg"; chmod 755 "$work"; [ "$(id -u)" = 0 ] && chown postgres "$work/pg"
as_pg "$PGBIN/initdb" -D "$work/pg/data" -U stillmap --auth=trust --no-sync -E UTF8 >"$work/initdb.log" 2>&1 \
  || { echo "cluster-demo: initdb failed:" >&2; cat "$work/initdb.log" >&2; exit 1; }
as_pg "$PGBIN/pg_ctl" -D "$work/pg/data" -w -l "$work/pg/log" \
  -o "-p $PGPORT -k $work/pg -c listen_addresses=127.0.0.1 -c fsync=off" start >/dev/null \
  || { echo "cluster-demo: PostgreSQL did not start:" >&2; cat "$work/pg/log" >&2; exit 1; }
REPLICA=postgresql://stillmap@127.0.0.1:$PGPORT/postgres

"$BIN/stillmap-router" --listen "$ROUTER" >"$work/router" 2>"$work/router.err" & pids+=($!)
wait_for "$work/router" ready "the router"
declare -A grpc http spid
start_server() { # name index
  grpc[$1]=127.0.0.1:$((BASE + 10 + $2)); http[$1]=127.0.0.1:$((BASE + 20 + $2))
  "$BIN/stillmap-server" --server-id "$1" --grpc-listen "${grpc[$1]}" --http-listen "${http[$1]}" \
    --zenoh-listen "tcp/127.0.0.1:$((BASE + 30 + $2))" --zenoh-connect "$ROUTER" --store "$work/$1.redb" "${perception[@]}" \
    --replica-url "$REPLICA" \
    >"$work/$1" 2>"$work/$1.err" & spid[$1]=$!; pids+=($!)
  wait_for "$work/$1" ready "$1"
}
start_server server-a 1
start_server server-b 2
for _ in $(seq 100); do
  n=$("$BIN/stillmap-client" servers --zenoh-connect "$ROUTER" --json | json 'min(len(s.get("servers", [])) for s in d) if len(d) == 2 else 0')
  [ "$n" = 2 ] && break; sleep 0.1
done
echo "== servers on the router"; "$BIN/stillmap-client" servers --zenoh-connect "$ROUTER"

echo; echo "== 4 robots stream $(basename "$TUM") at 30 Hz through the router"
robots=(robot-0 robot-1 robot-2 robot-3)
rpids=()
for r in "${robots[@]}"; do
  "$BIN/stillmap-client" stream --source "tum:$TUM" --transport zenoh --zenoh-connect "$ROUTER" --zenoh-mode client \
    --robot-id "$r" --rate 30 --quiet --summary-json "$work/$r.json" >/dev/null 2>"$work/$r.err" & rpids+=($!); pids+=($!)
done
sleep 1.5
placed() { # server -> robots streaming there
  curl -fsS "http://${http[$1]}/api/v1/sessions" | json '" ".join(sorted(s["robot_id"] for s in d["sessions"] if s["connected"] and s.get("server_id") == "'"$1"'"))'
}
a_robots=$(placed server-a); b_robots=$(placed server-b)
echo "placement: server-a: ${a_robots:-none} | server-b: ${b_robots:-none}"
session_of() { # server robot -> the robot's session id there
  curl -fsS "http://${http[$1]}/api/v1/sessions" | json '" ".join(s["session_id"] for s in d["sessions"] if s["robot_id"] == "'"$2"'")'
}
declare -A first_session
for r in "${robots[@]}"; do
  id=$(session_of server-a "$r"); [ -z "$id" ] && id=$(session_of server-b "$r")
  first_session[$r]=$id
  answered=()
  for s in server-a server-b; do
    curl -fsS -o /dev/null "http://${http[$s]}/api/v1/sessions/$id/pose" 2>/dev/null && answered+=("$s")
  done
  echo "  pose of $r ($id, on $(curl -fsS "http://${http[server-a]}/api/v1/sessions" | json '" ".join(s["server_id"] for s in d["sessions"] if s["session_id"] == "'"$id"'")')) answered by: ${answered[*]:-none}"
done

victim=server-b; [ -z "$b_robots" ] && victim=server-a
survivor=server-a; [ "$victim" = server-a ] && survivor=server-b
echo; echo "== kill -9 $victim"
kill -9 "${spid[$victim]}"
t0=$(date +%s%N)
wait "${spid[$victim]}" 2>/dev/null || true
want=$(printf '%s\n' "${robots[@]}" | sort | tr '\n' ' ' | sed 's/ $//')
moved=""
for _ in $(seq 200); do [ "$(placed $survivor)" = "$want" ] && { moved=1; break; }; sleep 0.025; done
t1=$(date +%s%N)
if [ -n "$moved" ]; then
  echo "all robots streaming on $survivor $(( (t1 - t0) / 1000000 )) ms after the kill"
else
  echo "not all robots streaming on $survivor $(( (t1 - t0) / 1000000 )) ms after the kill: $(placed $survivor)"
fi
for p in "${rpids[@]}"; do wait "$p"; done
printf '\n%-8s %6s %9s %16s %6s %6s  %s\n' robot sent answered "lost (in flight)" moved poses "session (same as at the start?)"
for r in "${robots[@]}"; do
  last=$(json 'd["session_id"]' <"$work/$r.json")
  poses=$(curl -fsS "http://${http[$survivor]}/api/v1/sessions/$last/trajectory" | json 'len(d["poses"])')
  same=no; [ "$last" = "${first_session[$r]}" ] && same=yes
  json '"%-8s %6d %9d %16d %6d" % ("'"$r"'", d["frames_sent"], d["frames_acknowledged"], d["frames_unanswered"], d["reconnects"])' <"$work/$r.json" \
    | tr -d '\n'; printf ' %6s  %s (%s)\n' "$poses" "$last" "$same"
done
metric() { curl -fsS "http://${http[$survivor]}/metrics" | awk -v m="$1" '$1 == m { print $2 }'; }
commits=$(metric stillmap_replica_commits_total); bytes=$(metric stillmap_replica_bytes_total)
micros=$(metric stillmap_replica_write_microseconds_total)
echo; echo "== replication to PostgreSQL ($survivor): $commits commits, $(( ${bytes%.*} / 1024 / (${commits%.*} > 0 ? ${commits%.*} : 1) )) KB and $(( ${micros%.*} / 1000 / (${commits%.*} > 0 ? ${commits%.*} : 1) )) ms per commit (a commit per keyframe)"

echo; echo "== latency per frame, 90 frames at 30 Hz to $survivor: through the router vs direct gRPC"
"$BIN/stillmap-client" stream --source "tum:$TUM" --transport zenoh --zenoh-connect "$ROUTER" --zenoh-mode client \
  --robot-id latency-zenoh --rate 30 --max-frames 90 --quiet --summary-json "$work/lz.json" >/dev/null
"$BIN/stillmap-client" stream --source "tum:$TUM" --transport grpc --server "http://${grpc[$survivor]}" \
  --robot-id latency-grpc --rate 30 --max-frames 90 --quiet --summary-json "$work/lg.json" >/dev/null
for f in lz lg; do
  json '"%-22s p50 %6.1f ms  p95 %6.1f ms" % ("zenoh via the router:" if "'"$f"'" == "lz" else "gRPC direct:", d["latency_ms_p50"], d["latency_ms_p95"])' <"$work/$f.json"
done

