"""Shape-function tuples [Ψ0, Ψ1, χ0, χ1] of Stachó's RSD C1 splines, as data.

A tuple is four functions with their first derivatives, vectorised over numpy arrays:

- Ψ0, Ψ1 on [0, 1] (univariate, with Ψ0', Ψ1'),
- χ0, χ1 on the simplex t1 + t2 + t3 = 1, t >= 0, given as functions of three independent
  variables with their three partial derivatives ∂/∂t1, ∂/∂t2, ∂/∂t3 (the paper's D1, D2, D3).

Named tuples (rsd-math.md, table "Named tuples from the paper"):
``sextic`` (Ex. 5.8, affine invariant, the default), ``quintic`` (the 2022 procedure,
Ex. 3.9a) and ``ex39b`` (Ex. 3.9b). A custom tuple is a :class:`ShapeTuple` of Python
callables (then check it with :func:`validate_tuple`) or comes from sympy expressions
(:func:`tuple_from_sympy`, which validates it). :func:`validate_tuple` checks
admissibility (2.1), the RSD conditions (3.6), (3.7) and that each derivative matches its
function, and refuses an invalid tuple naming the condition that failed. What a tuple
*reproduces* (constants, affine functions) is computed, not declared: see
:mod:`c1mesh.engine.properties`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from numpy.polynomial import Polynomial

from c1mesh.core.errors import C1MeshError, DependencyError

Univariate = Callable[[Any], Any]
Trivariate = Callable[[Any, Any, Any], Any]
TrivariateGrad = Callable[[Any, Any, Any], tuple]


class InvalidSchemeError(C1MeshError, ValueError):
    """A shape-function tuple violates a condition of the paper (named in the message)."""


@dataclass(frozen=True)
class ShapeTuple:
    """An RSD shape-function tuple with first derivatives.

    Every function accepts numpy arrays (broadcasting) and returns arrays of the same shape;
    ``psi0``, ``psi1`` (Ψ0, Ψ1) take t in [0, 1] and ``dpsi0``, ``dpsi1`` are their
    derivatives; ``chi0``, ``chi1`` (χ0, χ1) take (t1, t2, t3) and
    ``dchi0``/``dchi1`` return the triple (∂χ/∂t1, ∂χ/∂t2, ∂χ/∂t3). ``exact`` optionally
    holds the same eight functions accepting sympy objects (used for symbolic validation).
    ``degree`` is the polynomial degree when known, else None.

    A tuple of your own callables is built directly and checked before use::

        mine = ShapeTuple("mine", psi0, dpsi0, psi1, dpsi1, chi0, dchi0, chi1, dchi1)
        validate_tuple(mine)           # InvalidSchemeError naming the failed condition
    """

    name: str
    psi0: Univariate
    dpsi0: Univariate
    psi1: Univariate
    dpsi1: Univariate
    chi0: Trivariate
    dchi0: TrivariateGrad
    chi1: Trivariate
    dchi1: TrivariateGrad
    degree: int | None = None
    exact: "ShapeTuple | None" = field(default=None, repr=False, compare=False)
    description: str = ""


# --------------------------------------------------------------------------------------
# Polynomial tuples (the paper's named ones): exact derivatives from coefficients.
# --------------------------------------------------------------------------------------
class _Trivariate:
    """A polynomial in (t1, t2, t3) as {(a, b, c): coefficient}; callable and differentiable."""

    def __init__(self, terms: dict[tuple[int, int, int], float]):
        self.terms = {k: float(v) for k, v in terms.items() if v != 0}

    def __call__(self, t1, t2, t3):
        total = 0.0
        for (a, b, c), coef in self.terms.items():
            total = total + coef * t1**a * t2**b * t3**c
        return total

    def partial(self, q: int) -> "_Trivariate":
        """∂/∂t_(q+1), q in 0, 1, 2."""
        out: dict[tuple[int, int, int], float] = {}
        for exps, coef in self.terms.items():
            if exps[q]:
                lowered = list(exps)
                lowered[q] -= 1
                out[tuple(lowered)] = out.get(tuple(lowered), 0.0) + coef * exps[q]
        return _Trivariate(out)

    def gradient(self) -> TrivariateGrad:
        parts = [self.partial(q) for q in range(3)]
        return lambda t1, t2, t3: (parts[0](t1, t2, t3), parts[1](t1, t2, t3), parts[2](t1, t2, t3))

    @property
    def degree(self) -> int:
        return max((sum(k) for k in self.terms), default=0)


def _polynomial_tuple(name: str, psi0: list[float], psi1: list[float],
                      chi0: dict, chi1: dict, description: str) -> ShapeTuple:
    """Build a ShapeTuple from univariate coefficient lists (ascending powers) and monomial dicts."""
    p0, p1 = Polynomial(psi0), Polynomial(psi1)
    c0, c1 = _Trivariate(chi0), _Trivariate(chi1)
    degree = max(p0.degree(), p1.degree(), c0.degree, c1.degree)
    return ShapeTuple(name, p0, p0.deriv(), p1, p1.deriv(), c0, c0.gradient(), c1, c1.gradient(),
                      degree=degree, description=description)


PHI = [0, 0, 0, 10, -15, 6]    # Φ(t) = t³(10 − 15t + 6t²)
THETA = [0, 0, 0, 4, -3]       # Θ(t) = t³(4 − 3t)
_CHI0_30 = {(2, 2, 1): 30}     # 30 t1² t2² t3

SEXTIC = _polynomial_tuple(
    "sextic", PHI, PHI, _CHI0_30, {(2, 3, 1): 30, (2, 2, 2): 15},
    "Ex. 5.8: [Φ, Φ, 30t1²t2²t3, 30t1²t2³t3 + 15t1²t2²t3²], degree 6 (default)")
QUINTIC = _polynomial_tuple(
    "quintic", PHI, THETA, _CHI0_30, {(2, 2, 1): 12},
    "Ex. 3.9a, the 2022 procedure: [Φ, Θ, 30t1²t2²t3, 12t1²t2²t3], degree 5")
EX39B = _polynomial_tuple(
    "ex39b", PHI, PHI, _CHI0_30, {(2, 3, 1): 30},
    "Ex. 3.9b: [Φ, Φ, 30t1²t2²t3, 30t1²t2³t3], degree 6")

NAMED_TUPLES: dict[str, ShapeTuple] = {t.name: t for t in (SEXTIC, QUINTIC, EX39B)}
DEFAULT_SCHEME = "sextic"


def get_scheme(scheme: "str | ShapeTuple") -> ShapeTuple:
    """Return the tuple for a name in NAMED_TUPLES, or a ShapeTuple unchanged."""
    if isinstance(scheme, ShapeTuple):
        return scheme
    try:
        return NAMED_TUPLES[str(scheme).lower()]
    except KeyError:
        raise InvalidSchemeError(
            f"unknown scheme {scheme!r}; choose one of {', '.join(NAMED_TUPLES)}") from None


# --------------------------------------------------------------------------------------
# Custom tuples
# --------------------------------------------------------------------------------------
def tuple_from_sympy(psi0, psi1, chi0, chi1, t=None, t123=None, name: str = "custom",
                     validate: bool = True) -> ShapeTuple:
    """A tuple from sympy expressions: Ψ0, Ψ1 in the symbol ``t``; χ0, χ1 in ``t123``.

    Derivatives are derived symbolically; the numeric functions come from sympy.lambdify.
    ``t`` defaults to the single free symbol of Ψ0/Ψ1, ``t123`` to sympy.symbols('t1 t2 t3').
    Validation is symbolic (each condition must simplify to 0). Needs the optional sympy.
    """
    try:
        import sympy as sp
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise DependencyError("custom tuples from expressions need sympy: pip install sympy") from exc
    psi0, psi1, chi0, chi1 = (sp.sympify(e) for e in (psi0, psi1, chi0, chi1))
    if t is None:
        free = (psi0.free_symbols | psi1.free_symbols)
        t = free.pop() if len(free) == 1 else sp.Symbol("t")
    t1, t2, t3 = t123 if t123 is not None else sp.symbols("t1 t2 t3")
    derivs = [sp.diff(psi0, t), sp.diff(psi1, t)]
    grads = [[sp.diff(c, v) for v in (t1, t2, t3)] for c in (chi0, chi1)]

    def uni(expr):
        fn = sp.lambdify(t, expr, "numpy")
        return lambda x: np.asarray(x, float) * 0 + fn(x)  # broadcast constants

    def tri(expr):
        fn = sp.lambdify((t1, t2, t3), expr, "numpy")
        return lambda a, b, c: np.asarray(a, float) * 0 + fn(a, b, c)

    def tri_grad(exprs):
        fns = [tri(e) for e in exprs]
        return lambda a, b, c: tuple(f(a, b, c) for f in fns)

    def sym_uni(expr):
        return lambda x: expr.subs(t, x)

    def sym_tri(expr):
        return lambda a, b, c: expr.subs({t1: a, t2: b, t3: c}, simultaneous=True)

    def sym_grad(exprs):
        return lambda a, b, c: tuple(sym_tri(e)(a, b, c) for e in exprs)

    exact = ShapeTuple(name, sym_uni(psi0), sym_uni(derivs[0]), sym_uni(psi1), sym_uni(derivs[1]),
                       sym_tri(chi0), sym_grad(grads[0]), sym_tri(chi1), sym_grad(grads[1]))
    degree = None
    try:
        degree = max(sp.Poly(psi0, t).total_degree(), sp.Poly(psi1, t).total_degree(),
                     sp.Poly(chi0, t1, t2, t3).total_degree(), sp.Poly(chi1, t1, t2, t3).total_degree())
    except sp.PolynomialError:
        pass
    tup = ShapeTuple(name, uni(psi0), uni(derivs[0]), uni(psi1), uni(derivs[1]),
                     tri(chi0), tri_grad(grads[0]), tri(chi1), tri_grad(grads[1]),
                     degree=degree, exact=exact)
    if validate:
        validate_tuple(tup)
    return tup


# --------------------------------------------------------------------------------------
# Validation: admissibility (2.1) and the RSD conditions (3.6), (3.7)
# --------------------------------------------------------------------------------------
def _conditions(p: ShapeTuple):
    """Yield (condition name, residual function of t on [0, 1]) pairs; each must vanish.

    Written with arithmetic only, so the same code runs on numpy arrays and sympy symbols.
    """
    one = lambda t: 1 - t  # noqa: E731
    yield "(2.1) Ψ0(0) = 0", lambda t: p.psi0(0 * t)
    yield "(2.1) Ψ0'(0) = 0", lambda t: p.dpsi0(0 * t)
    yield "(2.1) Ψ1(0) = 0", lambda t: p.psi1(0 * t)
    yield "(2.1) Ψ1'(0) = 0", lambda t: p.dpsi1(0 * t)
    yield "(2.1) Ψ0'(1) = 0", lambda t: p.dpsi0(0 * t + 1)
    yield "(2.1) Ψ0(1) = 1", lambda t: p.psi0(0 * t + 1) - 1
    yield "(2.1) Ψ1(1) = 1", lambda t: p.psi1(0 * t + 1) - 1
    for r, (chi, dchi) in enumerate(((p.chi0, p.dchi0), (p.chi1, p.dchi1))):
        yield f"χ{r} vanishes on the edge t1 = 0", lambda t, c=chi: c(0 * t, t, one(t))
        yield f"χ{r} vanishes on the edge t2 = 0", lambda t, c=chi: c(t, 0 * t, one(t))
        yield f"χ{r} vanishes on the edge t3 = 0", lambda t, c=chi: c(t, one(t), 0 * t)
        for q in range(3):
            yield (f"(3.7) ∇χ{r} = 0 on the edge t1 = 0 (∂/∂t{q + 1})",
                   lambda t, d=dchi, q=q: d(0 * t, t, one(t))[q])
            yield (f"(3.7) ∇χ{r} = 0 on the edge t2 = 0 (∂/∂t{q + 1})",
                   lambda t, d=dchi, q=q: d(t, 0 * t, one(t))[q])
        for q in range(2):
            yield (f"(3.7) D{q + 1}χ{r} = 0 on the edge t3 = 0",
                   lambda t, d=dchi, q=q: d(t, one(t), 0 * t)[q])
    yield "(3.6) D3χ0(t, 1−t, 0) = Ψ0'(t)", lambda t: p.dchi0(t, one(t), 0 * t)[2] - p.dpsi0(t)
    yield ("(3.6) D3χ1(t, 1−t, 0) = Ψ1'(t)(1 − t)",
           lambda t: p.dchi1(t, one(t), 0 * t)[2] - p.dpsi1(t) * one(t))


def _derivative_checks(p: ShapeTuple):
    """Yield (name, function, derivative, variable index or None) for finite-difference checks."""
    yield "Ψ0' is the derivative of Ψ0", p.psi0, p.dpsi0, None
    yield "Ψ1' is the derivative of Ψ1", p.psi1, p.dpsi1, None
    for r, (chi, dchi) in enumerate(((p.chi0, p.dchi0), (p.chi1, p.dchi1))):
        for q in range(3):
            yield f"∂χ{r}/∂t{q + 1} is the derivative of χ{r}", chi, dchi, q


SAMPLES = 201  # a polynomial identity of degree < 201 holding at 201 points holds everywhere


def validate_tuple(p: ShapeTuple, tol: float = 1e-9) -> None:
    """Raise InvalidSchemeError naming the first condition of the paper that ``p`` violates.

    Symbolic (sympy ``simplify``) when the tuple carries exact expressions; otherwise each
    condition is sampled at 201 points of [0, 1] (for polynomial tuples of degree < 201
    that decides the identity up to round-off) and derivatives are checked against central
    finite differences at interior sample points.
    """
    if p.exact is not None:
        _validate_symbolic(p.exact)
        return
    t = np.linspace(0.0, 1.0, SAMPLES)
    for name, residual in _conditions(p):
        with np.errstate(all="ignore"):
            worst = float(np.max(np.abs(np.broadcast_to(residual(t), t.shape))))
        if not worst <= tol:
            raise InvalidSchemeError(f"{p.name}: condition {name} fails (off by {worst:.3g})")
    _check_derivatives(p)


def _validate_symbolic(exact: ShapeTuple) -> None:
    import sympy as sp
    t = sp.Symbol("t", real=True)
    for name, residual in _conditions(exact):
        if sp.simplify(sp.expand(residual(t))) != 0:
            raise InvalidSchemeError(f"{exact.name}: condition {name} fails (symbolically nonzero)")


def _check_derivatives(p: ShapeTuple, step: float = 1e-5, rtol: float = 1e-5) -> None:
    rng = np.random.default_rng(12345)
    s = rng.uniform(0.05, 0.95, size=(3, 64))
    for name, fn, deriv, q in _derivative_checks(p):
        with np.errstate(all="ignore"):
            if q is None:
                x = s[0]
                numeric = (fn(x + step) - fn(x - step)) / (2 * step)
                given = deriv(x)
            else:
                plus, minus = s.copy(), s.copy()
                plus[q] += step
                minus[q] -= step
                numeric = (fn(*plus) - fn(*minus)) / (2 * step)
                given = np.broadcast_to(deriv(*s)[q], numeric.shape)
            scale = 1.0 + float(np.max(np.abs(numeric)))
            worst = float(np.max(np.abs(given - numeric)))
        if not worst <= rtol * scale:
            raise InvalidSchemeError(f"{p.name}: {name} fails (off by {worst:.3g} vs finite differences)")
