#!/usr/bin/env bash
# Sets up everything c1mesh needs on a fresh Debian machine, from this repository's own files:
# the Debian packages it needs (libusb-1.0-0, a C compiler), a virtual environment in .venv, and the
# package with its dev extra (tests, matplotlib peer, sympy) installed editable.
#
# The build: meson-python (pyproject.toml, meson.build) compiles c1mesh's Cython kernels with the
# C compiler. The install is meson-python's editable one: it needs its build
# requirements in the venv first (--no-build-isolation) and ninja, builds into build/cp3XX/ and
# rebuilds a changed kernel when c1mesh is imported; the .py files are used from src/ as they
# are. An editable wheel carries no scripts, so the `c1mesh` launcher (bin/c1mesh) is copied into
# .venv/bin here (`pip install .` installs it by itself).
set -euo pipefail
cd "$(dirname "$0")"
# Debian packages: libusb-1.0-0 for open3d; a C compiler for
# c1mesh's kernels and for python-lzf, which PyPI has only as source (the PCD reader's LZF decoder).
missing=()
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)
command -v cc >/dev/null 2>&1 || missing+=(build-essential)
# SuiteSparse's headers for scikit-sparse (CHOLMOD, the smoothing fit's fastest solver, built
# from source against them); without them the fit uses scipy's SuperLU (same results).
# libopenblas0-pthread: Debian's reference BLAS would make CHOLMOD's supernodal factor ~2x slower.
[ -e /usr/include/suitesparse/cholmod.h ] || missing+=(libsuitesparse-dev libopenblas0-pthread)
if [ ${#missing[@]} -gt 0 ]; then
    if [ "$(id -u)" = 0 ]; then
        apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
    else
        echo "setup.sh: please install the Debian packages ${missing[*]}" >&2
    fi
fi
[ -x .venv/bin/python ] || python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
# the build requirements of pyproject.toml's [build-system], for the build without isolation;
# setuptools >= 70.1 (its own bdist_wheel) for python-lzf's sdist, which the venv's bundled
# setuptools cannot turn into a wheel without isolation
.venv/bin/python -m pip install -q "meson-python>=0.16" "meson>=1.4" ninja "cython>=3.0" "setuptools>=70.1"
# NINJA: the editable install runs `ninja -n` at every import of c1mesh to see whether a .pyx
# changed; naming the venv's binary keeps a PATH shim (pyenv's, asdf's: bash scripts, measured
# 46 ms a call against 3 ms) out of every command's start
NINJA="$PWD/.venv/bin/ninja" .venv/bin/python -m pip install -q --no-build-isolation -e '.[dev]'
if [ -e /usr/include/suitesparse/cholmod.h ]; then
    NINJA="$PWD/.venv/bin/ninja" .venv/bin/python -m pip install -q --no-build-isolation -e '.[dev,cholmod]' ||
        echo "setup.sh: scikit-sparse did not build; the smoothing fit will use SuperLU" >&2
fi
install -m 755 bin/c1mesh .venv/bin/c1mesh
# Bytecode for src's modules, which the editable install leaves uncompiled (`pip install .`
# compiles them). Python reads it even where PYTHONDONTWRITEBYTECODE keeps it from writing its
# own cache (container images often set it); without it every command compiled c1mesh's modules
# again: importing the fit took 0.42 s instead of 0.28. A module edited later is compiled in
# memory until this runs again; nothing stale is used.
.venv/bin/python -m compileall -q src/c1mesh
echo "setup.sh: ready (.venv/bin/c1mesh)" >&2
