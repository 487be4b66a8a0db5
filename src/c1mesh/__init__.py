"""c1mesh: smooth C1 surface meshes from scanned points with normals.

The engine is Stacho's reduced-side-derivative (RSD) C1 spline: `RSDInterpolator` is built
from points, values and gradients like scipy's interpolators, and `refine` evaluates it on
a uniform subdivision of every triangle as one matrix product.
"""
from __future__ import annotations

__version__ = "0.1.0"

from c1mesh.errors import C1MeshError, InputError, NotAHeightFieldError  # noqa: F401
from c1mesh.interpolator import RSDInterpolator  # noqa: E402,F401
from c1mesh.refine import RefinedMesh  # noqa: E402,F401
from c1mesh.schemes import NAMED_TUPLES, ShapeTuple, get_scheme  # noqa: E402,F401
