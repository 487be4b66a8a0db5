#!/usr/bin/env bash
# Installs the optional peers of the benchmarks: GMT (the `gmt` binary: blockmedian, surface,
# grdtrack) from Debian, and verde (benchmarks/heldout.py) and Shewchuk's Triangle (PyPI
# `triangle`, non-commercial licence: benchmarks/stages.py's floor job) into the project's
# .venv. CI does not need them: a benchmark skips an absent peer and says so.
set -euo pipefail
cd "$(dirname "$0")/.."
if command -v gmt >/dev/null 2>&1; then
    echo "install-peers.sh: gmt $(gmt --version) already installed" >&2
elif [ "$(id -u)" = 0 ]; then
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq gmt >/dev/null
else
    echo "install-peers.sh: run as root, or install the Debian package gmt yourself" >&2
fi
.venv/bin/python -m pip install -q verde triangle
echo "install-peers.sh: ready (gmt: $(command -v gmt || echo absent))" >&2
