#!/usr/bin/env bash
# Frames/s one session sustains through each transport (client --rate max, the
# whole current pipeline), and bytes per frame on the wire, on the real TUM clip.
# Usage: deploy/bench-transport.sh <bin-dir>
set -euo pipefail
BIN=${1:?usage: bench-transport.sh <bin-dir>}
export STILLMAP_DEMO_RATE=max
exec "$(dirname "$0")/demo.sh" "$BIN" --quiet
