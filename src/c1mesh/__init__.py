"""c1mesh: smooth C1 surface meshes from scanned points with normals.

A few verbs and types, like laspy's:

    import c1mesh
    result = c1mesh.fit("scan.ply", "surface.ply", c1mesh.FitOptions(level=3))
    result.report["points"]            # what the CLI's --report writes
    cloud = c1mesh.read_cloud("scan.laz", classes=(2,))

`fit` runs the whole pipeline on one input, or on a list of inputs as one survey (in
memory, or in tiles beyond options.memory, as the CLI does);
`read_cloud` / `write_mesh` are the format registry; `RSDInterpolator` is Stacho's
reduced-side-derivative C1 spline built from points, values and gradients like scipy's
interpolators, and `Refinement` evaluates it on a uniform subdivision of every triangle
as one matrix product. Errors are `C1MeshError` and its subclasses.

The names are imported on first use (PEP 562), so that `import c1mesh` and the `c1mesh`
command's --help and usage errors do not load numpy and scipy.
"""
from __future__ import annotations

__version__ = "0.1.0"

from c1mesh.core.errors import (C1MeshError, DependencyError, FormatError, InputError,  # noqa: F401
                                NotAHeightFieldError)

_LAZY = {
    "fit": "c1mesh.pipeline.run",
    "FitOptions": "c1mesh.pipeline.driver",
    "FitResult": "c1mesh.pipeline.driver",
    "read_cloud": "c1mesh.formats",
    "write_mesh": "c1mesh.formats",
    "PointCloud": "c1mesh.core.cloud",
    "SurfaceMesh": "c1mesh.core.cloud",
    "RSDInterpolator": "c1mesh.engine.interpolator",
    "Refinement": "c1mesh.engine.refine",
    "RefinedMesh": "c1mesh.engine.refine",
    "TileError": "c1mesh.survey.tiles",
    "NAMED_TUPLES": "c1mesh.engine.schemes",
    "ShapeTuple": "c1mesh.engine.schemes",
    "get_scheme": "c1mesh.engine.schemes",
}

__all__ = ["C1MeshError", "DependencyError", "FormatError", "InputError", "NotAHeightFieldError",
           "__version__", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'c1mesh' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))
