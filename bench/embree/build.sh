#!/usr/bin/env bash
# Build the Embree all-hits benchmark: bench/embree/build.sh [OUT_DIR]
# OUT_DIR defaults to this script's directory; the binary is OUT_DIR/trace.
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
out="${1:-$here}"
cc="${CC:-cc}"

if ! printf '#include <embree3/rtcore.h>\n' | "$cc" -E -x c - >/dev/null 2>&1; then
    echo "build.sh: <embree3/rtcore.h> not found; install Embree 3 with:" >&2
    echo "    apt-get install -y libembree-dev" >&2
    exit 2
fi

mkdir -p "$out"
"$cc" -O3 -march=native -Wall -Wextra -o "$out/trace" "$here/trace.c" -lembree3 -lpthread -lm
echo "$out/trace"
