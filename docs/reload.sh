#!/usr/bin/env bash
# What a timeline dropped from memory costs to bring back (issue 19's measurement):
#
#   docs/reload.sh SCENE 'QUERY'      e.g.  docs/reload.sh scenes/level.gltf 'fps=6'
#
# Starts `radiosity serve` (the release build) on a free port with a fresh data directory and
# a resident budget of one byte (no finished timeline keeps its traced state), posts SCENE with
# QUERY, and prints: the trace's seconds, the traced state's bytes in memory and in traced.bin,
# the seconds it took to write, then the seconds a preview waits and the rebuild's own seconds,
# first with the traced state read back from traced.bin, then with traced.bin removed (traced
# again from the stored scene), in one run.
set -euo pipefail
cd "$(dirname "$0")/.."
scene=$1
query=$2
port=$((20000 + RANDOM % 10000))
data=$(mktemp -d)
./target/release/radiosity serve --addr "127.0.0.1:$port" --data-dir "$data" \
    --resident-gib 1e-9 >"$data.log" 2>&1 &
server=$!
trap 'kill $server; rm -rf "$data" "$data.log"' EXIT
base="http://127.0.0.1:$port"
until curl -sf "$base/healthz" >/dev/null; do sleep 0.2; done
field() { python3 -c "import json, sys; d = json.load(sys.stdin); print($1)"; }
id=$(curl -sf -X POST -H 'content-type: model/gltf+json' --data-binary @"$scene" \
    "$base/v1/timelines?$query" | field 'd["id"]')
until [ "$(curl -sf "$base/v1/timelines/$id" | field 'd["status"]')" = done ]; do sleep 0.5; done
curl -sf "$base/v1/timelines/$id" |
    field '"trace_seconds", round(d["timings"]["trace"], 2), "traced_MB_in_memory", round(d["memory"]["bytes"] / 1e6, 1)'
echo "traced_MB_on_disk $(python3 -c "import os; print(round(os.path.getsize('$data/$id/traced.bin') / 1e6, 1))")" \
    "write_seconds $(grep -o 'saved the traced state.*seconds=[0-9.]*' "$data.log" | sed 's/.*seconds=//' | cut -c1-5)"
for from in traced_state scene; do
    [ "$from" = scene ] && rm "$data/$id/traced.bin"
    wait=$(curl -s -o /dev/null -w '%{time_total}' "$base/v1/timelines/$id/frames/0/preview.png")
    curl -sf "$base/v1/timelines/$id" |
        field '"rebuilt_from", d["rebuilt_from"], "rebuild_seconds", round(d["rebuild_seconds"], 3), "preview_seconds", '"$wait"
done
