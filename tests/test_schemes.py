"""Shape-function tuples: named formulas, custom tuples, validation against the paper."""
from __future__ import annotations

import numpy as np
import pytest

from c1mesh import RSDInterpolator
from c1mesh.engine.properties import scheme_properties
from c1mesh.engine.schemes import (NAMED_TUPLES, SEXTIC, InvalidSchemeError, ShapeTuple, get_scheme,
                                   tuple_from_sympy, validate_tuple)


def test_named_tuples_are_the_table_formulas():
    """Spot values straight from rsd-math.md's table, computed by hand."""
    t = 0.3
    phi = t**3 * (10 - 15 * t + 6 * t**2)
    theta = t**3 * (4 - 3 * t)
    a, b, c = 0.2, 0.5, 0.3
    assert SEXTIC.psi0(t) == pytest.approx(phi) and SEXTIC.psi1(t) == pytest.approx(phi)
    assert NAMED_TUPLES["quintic"].psi1(t) == pytest.approx(theta)
    for name in NAMED_TUPLES:
        assert get_scheme(name).chi0(a, b, c) == pytest.approx(30 * a**2 * b**2 * c)
    assert SEXTIC.chi1(a, b, c) == pytest.approx(30 * a**2 * b**3 * c + 15 * a**2 * b**2 * c**2)
    assert NAMED_TUPLES["quintic"].chi1(a, b, c) == pytest.approx(12 * a**2 * b**2 * c)
    assert NAMED_TUPLES["ex39b"].chi1(a, b, c) == pytest.approx(30 * a**2 * b**3 * c)
    assert [get_scheme(n).degree for n in ("sextic", "quintic", "ex39b")] == [6, 5, 6]


@pytest.mark.parametrize("name", list(NAMED_TUPLES))
def test_named_tuples_pass_validation_and_derivatives_are_right(name):
    tup = get_scheme(name)
    validate_tuple(tup)
    rng = np.random.default_rng(0)
    s = rng.uniform(0.1, 0.9, (3, 50))
    h = 1e-6
    for chi, dchi in ((tup.chi0, tup.dchi0), (tup.chi1, tup.dchi1)):
        for q in range(3):
            plus, minus = s.copy(), s.copy()
            plus[q] += h
            minus[q] -= h
            np.testing.assert_allclose(dchi(*s)[q], (chi(*plus) - chi(*minus)) / (2 * h), atol=1e-6)


def _sextic_callables(**overrides):
    parts = dict(psi0=SEXTIC.psi0, dpsi0=SEXTIC.dpsi0, psi1=SEXTIC.psi1, dpsi1=SEXTIC.dpsi1,
                 chi0=SEXTIC.chi0, dchi0=SEXTIC.dchi0, chi1=SEXTIC.chi1, dchi1=SEXTIC.dchi1)
    parts.update(overrides)
    return parts


def test_custom_tuple_of_callables_gives_the_same_spline():
    custom = ShapeTuple("my-sextic", **_sextic_callables())
    validate_tuple(custom)
    rng = np.random.default_rng(1)
    pts = rng.random((60, 2))
    f, A = np.sin(pts[:, 0]), np.stack([np.cos(pts[:, 0]), 0 * pts[:, 1]], 1)
    q = rng.random((200, 2))
    np.testing.assert_allclose(RSDInterpolator(pts, f, A, scheme=custom)(q),
                               RSDInterpolator(pts, f, A, scheme="sextic")(q), atol=1e-14, equal_nan=True)
    props = scheme_properties(custom)
    assert props.reproduces_constants and props.reproduces_affine


@pytest.mark.parametrize("override, condition", [
    (dict(psi0=lambda t: t, dpsi0=lambda t: 1 + 0 * t), "Ψ0'(0) = 0"),
    (dict(psi1=lambda t: 0.5 * t**3, dpsi1=lambda t: 1.5 * t**2), "Ψ1(1) = 1"),
    (dict(chi0=lambda a, b, c: 30 * a**2 * b**2 * c + a * b,
          dchi0=lambda a, b, c: (60 * a * b**2 * c + b, 60 * a**2 * b * c + a, 30 * a**2 * b**2)),
     "χ0 vanishes on the edge t3 = 0"),
    (dict(chi1=lambda a, b, c: 12 * a**2 * b**2 * c,
          dchi1=lambda a, b, c: (24 * a * b**2 * c, 24 * a**2 * b * c, 12 * a**2 * b**2)),
     "(3.6) D3χ1"),
    (dict(chi0=lambda a, b, c: 30 * a**2 * b**2 * c + 5 * a * b * c**2,
          dchi0=lambda a, b, c: (60 * a * b**2 * c + 5 * b * c**2, 60 * a**2 * b * c + 5 * a * c**2,
                                 30 * a**2 * b**2 + 10 * a * b * c)),
     "(3.7)"),
    (dict(psi1=lambda t: t, dpsi1=lambda t: 1 + 0 * t), "Ψ1'(0) = 0"),
])
def test_broken_custom_tuples_are_refused_naming_the_condition(override, condition):
    with pytest.raises(InvalidSchemeError, match=condition.replace("(", r"\(").replace(")", r"\)")):
        validate_tuple(ShapeTuple("broken", **_sextic_callables(**override)))


def test_a_wrong_derivative_is_caught():
    wrong = _sextic_callables(dchi1=lambda a, b, c: (SEXTIC.dchi1(a, b, c)[0] * 1.1,) + SEXTIC.dchi1(a, b, c)[1:])
    with pytest.raises(InvalidSchemeError, match="derivative"):
        validate_tuple(ShapeTuple("custom", **wrong))


def test_sympy_tuple_validated_symbolically_and_properties_computed():
    sp = pytest.importorskip("sympy")
    t = sp.Symbol("t")
    t1, t2, t3 = sp.symbols("t1 t2 t3")
    phi = t**3 * (10 - 15 * t + 6 * t**2)
    chi0 = 30 * t1**2 * t2**2 * t3
    tup = tuple_from_sympy(phi, phi, chi0, chi0 * (t2 + t3 / 2), t=t, t123=(t1, t2, t3), name="ex58")
    props = scheme_properties(tup)
    assert props.degree == 6 and props.reproduces_affine
    with pytest.raises(InvalidSchemeError, match=r"\(3\.6\) D3χ1"):
        tuple_from_sympy(phi, phi, chi0, chi0 * t2 / 2, t=t, t123=(t1, t2, t3))


def test_unknown_scheme_name():
    with pytest.raises(InvalidSchemeError, match="sextic"):
        get_scheme("septic")
