#!/usr/bin/env bash
# A bake traced in parts by N processes on this machine and merged, against one bake of the
# same lines (issue 18's measurement):
#
#   docs/shard.sh SCENE "N..." [bake options]     e.g.  docs/shard.sh scenes/level.gltf "2 4" --fps 6
#
# For the single bake and for each N: the seconds of the parts (all N at once), of the merge,
# and in all; the bytes of the parts; and whether the outputs are byte-identical to the single
# bake's (timings.json aside). The parts share this machine's cores, so the times say what
# sharding costs (the parts' trace against one trace, the merge's reading), not what N
# machines gain: each part traces 1/N of the lines.
set -euo pipefail
cd "$(dirname "$0")/.."
scene=$1
counts=$2
shift 2
# The outputs' options, which merge takes (the parts carry the others).
outputs=$(python3 -c '
import sys
args, kept, i = sys.argv[1:], [], 0
valued = ("--glb-frames", "--preview-frames", "--preview-size", "--exposure", "--preview-shading")
while i < len(args):
    name = args[i].split("=")[0]
    n = 2 if name in valued and "=" not in args[i] else 1
    if name in valued or name == "--no-gif":
        kept += args[i:i + n]
    i += n if name in valued else 1
print(" ".join(kept))' "$@")
radiosity=./target/release/radiosity
name=$(basename "${scene%.*}")
work=$(mktemp -d)
log=$(mktemp)
# The commands' own output goes to a log, printed if one of them fails.
trap 'status=$?; [ $status -ne 0 ] && tail -20 "$log"; rm -rf "$work" "$log"' EXIT
now() { date +%s.%N; }
since() { python3 -c "import sys; print(f'{float(sys.argv[2]) - float(sys.argv[1]):.2f}')" "$1" "$(now)"; }
start=$(now)
$radiosity bake "$scene" --out "$work/single" "$@" 2>>"$log"
echo "single: $(since "$start") s; trace $(python3 -c "import json; t = json.load(open('$work/single/$name/timings.json')); print(round(t['trace'], 2), 's of it')")"
for n in $counts; do
    out="$work/n$n"
    start=$(now)
    for k in $(seq 0 $((n - 1))); do
        $radiosity bake "$scene" --shard "$k/$n" --out "$out" "$@" 2>>"$log" &
    done
    for k in $(seq 1 "$n"); do wait -n; done
    parts=$(since "$start")
    start=$(now)
    $radiosity merge "$out/$name"/shard-*.part --out "$out" $outputs 2>>"$log"
    merge=$(since "$start")
    bytes=$(du -cb "$out/$name"/shard-*.part | tail -1 | cut -f1)
    if diff -r -q -x '*.part' -x timings.json "$work/single/$name" "$out/$name" >/dev/null; then
        same=identical
    else
        same=DIFFERENT
    fi
    echo "N=$n: parts $parts s (at once), merge $merge s, parts $((bytes / 1000000)) MB in all; outputs $same"
done
