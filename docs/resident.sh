#!/usr/bin/env bash
# Resident memory of the service over jobs in a row (issue 19's measurement):
#
#   docs/resident.sh JOBS [serve options...]     e.g.  docs/resident.sh 12 --resident-gib 0.25
#
# Starts `radiosity serve` (the release build) on a free port with a fresh data directory,
# posts the moving Cornell box (1M lines, 12 fps: 25 frames) JOBS times, one after the other,
# and after each prints: job, resident MiB, traced MiB, timelines traced in memory, data MiB.
set -euo pipefail
cd "$(dirname "$0")/.."
jobs=$1
shift
port=$((20000 + RANDOM % 10000))
data=$(mktemp -d)
./target/release/radiosity serve --addr "127.0.0.1:$port" --data-dir "$data" "$@" >"$data.log" 2>&1 &
server=$!
trap 'kill $server; rm -rf "$data" "$data.log"' EXIT
base="http://127.0.0.1:$port"
until curl -sf "$base/healthz" >/dev/null; do sleep 0.2; done
field() { python3 -c "import json, sys; print($1)"; }
echo "job resident_MiB traced_MiB traced_timelines data_MiB"
for i in $(seq 1 "$jobs"); do
    id=$(curl -sf -X POST -H 'content-type: model/gltf+json' --data-binary @scenes/cornell_moving.gltf \
        "$base/v1/timelines?lines=1000000&fps=12&seed=$i" | field 'json.load(sys.stdin)["id"]')
    until [ "$(curl -sf "$base/v1/timelines/$id" | field 'json.load(sys.stdin)["status"]')" = done ]; do
        sleep 0.5
    done
    curl -sf "$base/healthz" | python3 -c '
import json, sys
h = json.load(sys.stdin)
m = h["memory"]
print(sys.argv[1], m["resident_bytes"] >> 20, m["traced_bytes"] >> 20,
      h["timelines"]["traced_in_memory"], round(h["data_dir_bytes"] / 2**20, 1))' "$i"
done
