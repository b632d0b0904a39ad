#!/usr/bin/env bash
# The stage times of docs/speed.md's tables (issue 47): each bake run by each binary given (a
# build of this commit and, say, one of an earlier commit), the binaries alternated bake by
# bake and the whole set repeated ROUNDS times (default 1), so that a machine growing busier or
# quieter weighs on every binary alike; one row per run as it finishes, in seconds from the
# bake's timings.json:
#
#   [ROUNDS=2] docs/speed.sh [BINARY...]          (default: ./target/release/radiosity)
#
# Run it on a quiet machine: the ratios between rows of one run are what it measures.
set -euo pipefail
cd "$(dirname "$0")/.."
binaries=("$@")
[ ${#binaries[@]} -eq 0 ] && binaries=(./target/release/radiosity)
bakes=(
  "scenes/level.gltf --preset default --fps 12"
  "scenes/cornell_moving.gltf --preset default --fps 30 --end 0"
  "scenes/cornell_moving.gltf --preset default --fps 30"
  "scenes/spheres.gltf --lines 4000000 --fps 10"
)
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
echo "| binary | bake | trace | split | solve | outputs | whole command | whole / trace |"
echo "|---|---|---|---|---|---|---|---|"
for _ in $(seq "${ROUNDS:-1}"); do
  for bake in "${bakes[@]}"; do
    for binary in "${binaries[@]}"; do
      read -r -a args <<<"$bake"
      rm -rf "$out/bake"
      start=$(date +%s.%N)
      "$binary" bake "${args[@]}" --no-gif --out "$out/bake" >/dev/null 2>&1
      end=$(date +%s.%N)
      name=$(basename "${args[0]%.*}")
      python3 - "$out/bake/$name/timings.json" "$start" "$end" "$binary" "$bake" <<'EOF'
import json, sys
t = json.load(open(sys.argv[1]))
whole = float(sys.argv[3]) - float(sys.argv[2])
stages = [t["trace"] + t["adapt"], t["split"], t["solve"], t["outputs"]]
cells = " | ".join(f"{s:.2f}" for s in stages)
print(f"| `{sys.argv[4]}` | `{sys.argv[5]}` | {cells} | {whole:.1f} | {whole / stages[0]:.1f} |")
EOF
    done
  done
done
