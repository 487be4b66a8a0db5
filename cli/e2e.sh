#!/usr/bin/env bash
# End-to-end check of the installed `c1mesh` command as a shell user meets it.
# Usage: bash cli/e2e.sh [c1mesh-command]   (default: c1mesh on PATH). Exits non-zero on
# the first broken promise of cli/README.md, printing which.
set -uo pipefail
C1MESH=${1:-c1mesh}
here="$(cd "$(dirname "$0")/.." && pwd)"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
failures=0

check() {  # check DESCRIPTION EXPECTED_EXIT ACTUAL_EXIT
    if [ "$2" != "$3" ]; then
        echo "FAIL: $1 (exit $3, expected $2)" >&2
        failures=$((failures + 1))
    else
        echo "ok: $1"
    fi
}

one_line_error() {  # the stderr file holds exactly one line starting with "c1mesh: error:"
    [ "$(wc -l < "$1")" -eq 1 ] && grep -q '^c1mesh: error: ' "$1" && ! grep -q Traceback "$1"
}

# A sample in, a mesh out, a report beside it.
$C1MESH fit "$here/data_samples/hill.ply" -o "$work/hill.ply" --level 3 --report "$work/hill.json" 2> "$work/err"
check "fit a PLY sample" 0 $?
[ -s "$work/hill.ply" ] && head -c 3 "$work/hill.ply" | grep -q ply
check "output is a PLY file" 0 $?
grep -q '"c1_certificate"' "$work/hill.json"
check "report has a C1 certificate" 0 $?
[ ! -s "$work/err" ]
check "quiet stderr when not a terminal" 0 $?

# stdin -> stdout
cat "$here/data_samples/wave_tilted_offset.xyz" | $C1MESH fit - --input-format xyz -o - --level 2 > "$work/piped.ply"
check "stdin to stdout" 0 $?
head -c 200 "$work/piped.ply" | grep -aq "binary_little_endian"
check "stdout carries binary PLY" 0 $?

# other output formats
for ext in obj stl off glb; do
    $C1MESH fit "$here/data_samples/hill.ply" -o "$work/hill.$ext" --level 1 -q
    check "write .$ext" 0 $?
done

# usage errors: exit 2
$C1MESH fit "$here/data_samples/hill.ply" 2> /dev/null
check "missing -o is a usage error" 2 $?
$C1MESH fit - -o "$work/x.ply" < /dev/null 2> /dev/null
check "stdin without --input-format is a usage error" 2 $?
$C1MESH fit "$here/data_samples/hill.ply" -o "$work/x.ply" --level zero 2> /dev/null
check "bad option value is a usage error" 2 $?

# failures: exit 1, one line, no output file
$C1MESH fit "$work/missing.ply" -o "$work/missing_out.ply" 2> "$work/err"
check "missing input fails" 1 $?
one_line_error "$work/err" && [ ! -e "$work/missing_out.ply" ]
check "missing input: one clear line, no output" 0 $?
printf 'ply\nformat binary_little_endian 1.0\nelement vertex 1000\nproperty float x\nproperty float y\nproperty float z\nend_header\n' > "$work/trunc.ply"
head -c 100 /dev/urandom >> "$work/trunc.ply"
$C1MESH fit "$work/trunc.ply" -o "$work/trunc_out.ply" 2> "$work/err"
check "truncated PLY fails" 1 $?
one_line_error "$work/err" && [ ! -e "$work/trunc_out.ply" ]
check "truncated PLY: one clear line, no output" 0 $?
$C1MESH fit "$here/data_samples/o3d_cloud_bin_0.pcd" -o "$work/room.ply" 2> "$work/err"
check "a room (not a height field) fails" 1 $?
grep -qi "height field" "$work/err" && [ ! -e "$work/room.ply" ]
check "the refusal says 'height field'" 0 $?
cp "$here/data_samples/hill.ply" "$work/same.ply"
$C1MESH fit "$work/same.ply" -o "$work/same.ply" 2> "$work/err"
check "output = input is refused" 1 $?
cmp -s "$work/same.ply" "$here/data_samples/hill.ply"
check "the input is untouched" 0 $?
$C1MESH fit "$here/data_samples/hill.ply" -o "$work/no/such/dir/out.ply" 2> "$work/err"
check "unwritable output location fails" 1 $?

# batch with one bad file: exit 3, the good ones written
mkdir -p "$work/batch"
cp "$here/data_samples/hill.ply" "$work/batch/a.ply"
printf 'garbage' > "$work/batch/b.ply"
$C1MESH fit "$work/batch/a.ply" "$work/batch/b.ply" -O "$work/out" --level 1 --jobs 2 2> "$work/err"
check "batch with a bad file exits 3" 3 $?
[ -s "$work/out/a.c1.ply" ] && [ ! -e "$work/out/b.c1.ply" ] && grep -q "b.ply" "$work/err"
check "batch wrote the good file and named the bad one" 0 $?

# info and schemes
$C1MESH info "$here/data_samples/hill.ply" > "$work/info.json"
check "info" 0 $?
grep -q '"height_field": true' "$work/info.json"
check "info says the sample is a height field" 0 $?
$C1MESH schemes > "$work/schemes.txt"
check "schemes" 0 $?
grep -q "^sextic" "$work/schemes.txt"
check "schemes lists sextic" 0 $?

if [ "$failures" -ne 0 ]; then
    echo "$failures check(s) failed" >&2
    exit 1
fi
echo "all end-to-end checks passed"
