#!/usr/bin/env bash
# Shell use of c1mesh: a folder batch and a stdin -> stdout chain.
# Run: bash examples/batch_and_pipe.sh [c1mesh-command]   (default: c1mesh on PATH, else .venv/bin/c1mesh)
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
# The command: the argument, else c1mesh on PATH, else the one ./setup.sh put in .venv.
if [ -n "${1:-}" ]; then C1MESH=$1
elif command -v c1mesh > /dev/null; then C1MESH=c1mesh
elif [ -x "$here/.venv/bin/c1mesh" ]; then C1MESH="$here/.venv/bin/c1mesh"
else echo "$(basename "$0"): no c1mesh on PATH and no $here/.venv/bin/c1mesh; run ./setup.sh" >&2; exit 127
fi
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

# 1. A folder of scans -> one mesh each, two processes, a JSON report of the batch.
mkdir -p "$work/scans"
cp "$here/data_samples/hill.ply" "$here/data_samples/wave_tilted_offset.xyz" "$work/scans/"
$C1MESH fit "$work"/scans/* -O "$work/meshes" --jobs 2 --level 3 --report "$work/batch.json" -q
ls "$work/meshes"

# 2. A pipe: text points on stdin, binary PLY on stdout, into the next tool.
cat "$here/data_samples/wave_tilted_offset.xyz" \
  | $C1MESH fit - --input-format xyz -o - --level 2 -q \
  > "$work/piped.ply"
head -c 300 "$work/piped.ply" | grep -a "element vertex"
