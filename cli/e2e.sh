#!/usr/bin/env bash
# End-to-end check of the installed `c1mesh` command as a shell user meets it.
# Usage: bash cli/e2e.sh [c1mesh-command]   (default: c1mesh on PATH, else .venv/bin/c1mesh). Exits non-zero on
# the first broken promise of cli/README.md, printing which.
set -uo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
# The command: the argument, else c1mesh on PATH, else the one ./setup.sh put in .venv.
if [ -n "${1:-}" ]; then C1MESH=$1
elif command -v c1mesh > /dev/null; then C1MESH=c1mesh
elif [ -x "$here/.venv/bin/c1mesh" ]; then C1MESH="$here/.venv/bin/c1mesh"
else echo "$(basename "$0"): no c1mesh on PATH and no $here/.venv/bin/c1mesh; run ./setup.sh" >&2; exit 127
fi
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

# outputs never destroy inputs or each other (cli/README.md, "Output paths")
$C1MESH fit "$work/same.ply" -o "$work/r_out.ply" --report "$work/same.ply" 2> "$work/err"
check "report = input is refused" 1 $?
cmp -s "$work/same.ply" "$here/data_samples/hill.ply" && one_line_error "$work/err" && [ ! -e "$work/r_out.ply" ]
check "report = input: input untouched, one line, no mesh" 0 $?
$C1MESH fit "$work/same.ply" -o "$work/twice.ply" --report "$work/twice.ply" 2> "$work/err"
check "report = mesh is refused" 1 $?
cp "$here/data_samples/hill.ply" "$work/same.c1.ply"
$C1MESH fit "$work/same.ply" "$work/same.c1.ply" -O "$work" --jobs 2 2> "$work/err"
check "batch output = a later input is refused" 1 $?
cmp -s "$work/same.c1.ply" "$here/data_samples/hill.ply"
check "the later input is untouched" 0 $?
$C1MESH fit - --input-format ply -o "$work/same.ply" < "$work/same.ply" 2> "$work/err"
check "-o = the file on stdin is refused" 1 $?
$C1MESH fit "$work/same.ply" -o "$work/nomesh.ply" --report /dev/full --level 1 2> "$work/err"
check "a report that cannot be written fails" 1 $?
[ ! -e "$work/nomesh.ply" ] && one_line_error "$work/err"
check "... and leaves no mesh behind" 0 $?
printf 'old' > "$work/private.ply" && chmod 600 "$work/private.ply"
$C1MESH fit "$work/same.ply" -o "$work/private.ply" --level 1
check "overwrite an existing output" 0 $?
[ "$(stat -c %a "$work/private.ply")" = 600 ]
check "an existing output keeps its mode 0600" 0 $?
$C1MESH fit "$work/same.ply" -o /dev/null --report /dev/null --level 1
check "/dev/null as mesh and report" 0 $?
[ -c /dev/null ]
check "/dev/null is still a character device" 0 $?
$C1MESH fit "$work/same.ply" -o /dev/stdout --level 1 > "$work/stdout.ply" && head -c 3 "$work/stdout.ply" | grep -q ply
check "-o /dev/stdout writes the mesh to stdout" 0 $?
$C1MESH fit "$work/same.ply" -o "$work/x.xyz" 2> "$work/err"
check "unsupported output extension is a usage error" 2 $?
if ls -A "$work" | grep -q '\.tmp$'; then false; else true; fi
check "no temporary files are left" 0 $?

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
