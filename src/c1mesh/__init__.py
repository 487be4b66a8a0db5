"""c1mesh: smooth C1 surface meshes from scanned points with normals.

The engine is Stacho's reduced-side-derivative (RSD) C1 spline: `RSDInterpolator` is built
from points, values and gradients like scipy's interpolators, and `refine` evaluates it on
a uniform subdivision of every triangle as one matrix product.

The numerical names below are imported on first use (PEP 562), so that `import c1mesh`
and the `c1mesh` command's --help and usage errors do not load numpy and scipy.
"""
from __future__ import annotations

__version__ = "0.1.0"

from c1mesh.core.errors import C1MeshError, InputError, NotAHeightFieldError  # noqa: F401

_LAZY = {
    "RSDInterpolator": "c1mesh.engine.interpolator",
    "RefinedMesh": "c1mesh.engine.refine",
    "NAMED_TUPLES": "c1mesh.engine.schemes",
    "ShapeTuple": "c1mesh.engine.schemes",
    "get_scheme": "c1mesh.engine.schemes",
}

__all__ = ["C1MeshError", "InputError", "NotAHeightFieldError", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'c1mesh' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
