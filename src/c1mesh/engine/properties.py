"""What a shape-function tuple reproduces, found by evaluating it — never declared.

A tuple reproduces a function class when, on random triangles with random (non-parallel)
edge directions, the spline of that class's exact first-order data equals the function
to round-off. Constants test the range shift property (Prop. 4.4), affine functions the
affinity invariance (Prop. 5.6). Named and custom tuples get the same honest report.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from c1mesh.engine import rsd
from c1mesh.engine.schemes import ShapeTuple, get_scheme

_REPRODUCES = 1e-9  # relative defect below which a class counts as reproduced


@dataclass(frozen=True)
class SchemeProperties:
    """Computed properties of a tuple; defects are the largest relative errors seen."""

    name: str
    degree: int | None
    reproduces_constants: bool
    reproduces_affine: bool
    constant_defect: float
    affine_defect: float

    def as_dict(self) -> dict:
        return asdict(self)


def _random_triangles(rng, trials: int) -> tuple[np.ndarray, np.ndarray]:
    """Random well-posed triangles (T, 3, 2) and random edge directions (T, 3, 2)."""
    corners = rng.normal(size=(trials, 3, 2))
    directions = rng.normal(size=(trials, 3, 2))
    return corners, directions


def _defect(scheme: ShapeTuple, corners, directions, f, grad_f, rng) -> float:
    """Largest relative error of the spline of (f, ∇f) against f and ∇f inside the triangles."""
    G, _ = rsd.barycentric_gradients(corners)
    values = f(corners)
    grads = grad_f(corners)
    C = rsd.triangle_coefficients(corners, values, grads, directions, G)
    lam = rng.dirichlet(np.ones(3), size=64)
    x = np.einsum("pk,tkd->tpd", lam, corners)
    F = C @ rsd.basis(scheme, lam)
    D0, D1 = rsd.gradient_basis(scheme, lam)
    dF = (C @ D0)[..., None] * G[:, None, 0] + (C @ D1)[..., None] * G[:, None, 1]
    scale = 1.0 + np.abs(f(x)).max()
    return float(max(np.abs(F - f(x)).max(), np.abs(dF - grad_f(x)).max()) / scale)


def scheme_properties(scheme: "str | ShapeTuple", trials: int = 200, seed: int = 0) -> SchemeProperties:
    """Evaluate whether ``scheme`` reproduces constants and affine functions (see module doc)."""
    scheme = get_scheme(scheme)
    rng = np.random.default_rng(seed)
    corners, directions = _random_triangles(rng, trials)
    c = rng.normal()
    a, b = rng.normal(size=2), rng.normal()
    const = _defect(scheme, corners, directions,
                    lambda x: np.full(x.shape[:-1], c), lambda x: np.zeros(x.shape), rng)
    affine = _defect(scheme, corners, directions,
                     lambda x: x @ a + b, lambda x: np.broadcast_to(a, x.shape), rng)
    return SchemeProperties(scheme.name, scheme.degree, bool(const < _REPRODUCES),
                            bool(affine < _REPRODUCES), const, affine)
