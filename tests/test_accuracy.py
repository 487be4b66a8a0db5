"""The sextic's accuracy and smoothness measured from outside: convergence orders on a
sequence of meshes, and C1 continuity by finite differences of evaluated values only.

Neither test uses the package's basis derivatives (RSDInterpolator.gradient is used only
to measure the gradient's convergence order, against exact analytic gradients).
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import Delaunay

from c1mesh import RSDInterpolator

from c1mesh.engine import rsd


def smooth(xy):
    """f(x, y) = sin(2x + 1)·cos(3y) + exp(x·y)/2 and its exact gradient (N, 2)."""
    x, y = xy[:, 0], xy[:, 1]
    f = np.sin(2 * x + 1) * np.cos(3 * y) + np.exp(x * y) / 2
    fx = 2 * np.cos(2 * x + 1) * np.cos(3 * y) + y * np.exp(x * y) / 2
    fy = -3 * np.sin(2 * x + 1) * np.sin(3 * y) + x * np.exp(x * y) / 2
    return f, np.column_stack([fx, fy])


def jittered_grid(k: int, seed: int = 0) -> np.ndarray:
    """(k+1)² points of the unit square's k×k grid, interior ones moved by up to 0.2 h in
    each coordinate: a shape-regular family (angles bounded away from 0 as h = 1/k
    shrinks), which is what the approximation orders below are proved for."""
    g = np.stack(np.meshgrid(np.linspace(0, 1, k + 1), np.linspace(0, 1, k + 1)), -1).reshape(-1, 2)
    inner = np.all((g > 0) & (g < 1), axis=1)
    rng = np.random.default_rng(seed)
    g[inner] += rng.uniform(-0.2, 0.2, (int(inner.sum()), 2)) / k
    return g


# --- convergence orders -------------------------------------------------------------------

def test_sextic_converges_at_order_two_in_values_and_one_in_gradients():
    """Values O(h²), gradients O(h) (docs/rsd-math.md): the sextic reproduces affine
    functions (Stachó, Prop. 5.6) and its basis is affine invariant, so on shape-regular
    meshes the Bramble–Hilbert argument bounds the error by C·|D²f|·h² for values and
    C·|D²f|·h for gradients. Orders are measured per halving of h on a jittered grid with
    exact data, and must stay above 1.8 and 0.9 (0.9 × the proved orders) at every step."""
    c = (np.arange(100) + 0.5) / 100
    xe = np.stack(np.meshgrid(c, c), axis=-1).reshape(-1, 2)
    f_true, g_true = smooth(xe)
    value_rms, gradient_rms = [], []
    for k in (8, 16, 32, 64):
        pts = jittered_grid(k, seed=k)
        f, g = smooth(pts)
        interp = RSDInterpolator(pts, f, g, triangles=Delaunay(pts).simplices)
        value_rms.append(np.sqrt(np.mean((interp(xe) - f_true) ** 2)))
        gradient_rms.append(np.sqrt(np.mean(np.sum((interp.gradient(xe) - g_true) ** 2, axis=1))))
    value_orders = np.log2(np.array(value_rms[:-1]) / value_rms[1:])
    gradient_orders = np.log2(np.array(gradient_rms[:-1]) / gradient_rms[1:])
    assert np.all(value_orders >= 1.8), value_orders
    assert np.all(gradient_orders >= 0.9), gradient_orders


# --- C1 continuity by finite differences ----------------------------------------------------

def _crossings(tri: Delaunay, rng, count: int):
    """Points on `count` random interior edges (at 30-70 % of the edge), the edge's unit
    normal, the smaller of the two triangles' heights over the edge, and the two
    triangles on either side (minus side, plus side)."""
    simplices, neighbours = tri.simplices, tri.neighbors
    t, k = np.nonzero(neighbours >= 0)
    keep = t < neighbours[t, k]                             # each interior edge once
    t, k = t[keep], k[keep]
    pick = rng.choice(t.size, size=min(count, t.size), replace=False)
    t, k = t[pick], k[pick]
    a = tri.points[simplices[t, (k + 1) % 3]]
    b = tri.points[simplices[t, (k + 2) % 3]]
    along = a + rng.uniform(0.3, 0.7, (t.size, 1)) * (b - a)
    length = np.linalg.norm(b - a, axis=1)
    normal = np.column_stack([-(b - a)[:, 1], (b - a)[:, 0]]) / length[:, None]
    # orient the normal from triangle t (minus side) towards its neighbour (plus side)
    opposite = tri.points[simplices[t, k]]
    flip = np.einsum("ij,ij->i", opposite - along, normal) > 0
    normal[flip] *= -1
    other = neighbours[t, k]
    across = tri.points[simplices[other]].sum(axis=1) - a - b      # the plus side's apex
    height = np.minimum(np.abs(np.einsum("ij,ij->i", opposite - a, normal)),
                        np.abs(np.einsum("ij,ij->i", across - a, normal)))
    return along, normal, height, t, other


def normal_derivative_jumps(evaluate, tri: Delaunay, along, normal, height, minus, plus,
                            step: float):
    """|∂f/∂n from the plus side − ∂f/∂n from the minus side| at each crossing point, from
    values only: second-order one-sided differences f'(0±) ≈ ±(−3f(0) + 4f(±δ) − f(±2δ))/(2δ)
    with δ = step × the smaller triangle height over the edge. Crossings whose sample points leave the two triangles
    are returned as NaN."""
    delta = (step * height)[:, None]
    f0 = evaluate(along)
    side = {}
    for sign, home in ((1, plus), (-1, minus)):
        p1, p2 = along + sign * delta * normal, along + 2 * sign * delta * normal
        inside = (tri.find_simplex(p1) == home) & (tri.find_simplex(p2) == home)
        d = sign * (-3 * f0 + 4 * evaluate(p1) - evaluate(p2)) / (2 * delta[:, 0])
        side[sign] = np.where(inside, d, np.nan)
    return np.abs(side[1] - side[-1])


# δ / triangle height: small enough that the one-sided differences are in their δ² regime
# with random data (third derivatives ~ |g| / height² there), large enough that rounding
# (~1e-16 |f| / δ) stays far below the jumps being compared
STEPS = (2.5e-4, 1.25e-4, 6.25e-5)


@pytest.fixture(scope="module")
def random_mesh_data():
    """Random points with random values and gradients: C1 must hold for any first-order
    data, not just smooth ones (non-smooth data make the jumps of a C0 scheme large)."""
    rng = np.random.default_rng(5)
    pts = np.vstack([[[0, 0], [1, 0], [0, 1], [1, 1]], rng.random((300, 2))])
    tri = Delaunay(pts)
    f, g = rng.normal(size=len(pts)), rng.normal(size=(len(pts), 2))
    return tri, f, g, _crossings(tri, rng, 200)


def test_normal_derivative_is_continuous_across_interior_edges(random_mesh_data):
    """C1 from evaluated values only: the normal-derivative jump measured by one-sided
    differences shrinks like δ² (the differences' own error) for the sextic, while the
    piecewise-linear peer (scipy LinearNDInterpolator, C0 only) keeps jumps of O(1)."""
    tri, f, g, (along, normal, height, minus, plus) = random_mesh_data
    ours = RSDInterpolator(tri.points, f, g, triangles=tri.simplices)
    peer = LinearNDInterpolator(tri, f)
    scale = np.abs(g).max()
    jumps = np.array([normal_derivative_jumps(ours, tri, along, normal, height, minus, plus, s)
                      for s in STEPS])
    peer_jumps = normal_derivative_jumps(peer, tri, along, normal, height, minus, plus, STEPS[-1])
    measured = np.all(np.isfinite(jumps), axis=0) & np.isfinite(peer_jumps)
    assert measured.sum() >= 150
    jumps, peer_jumps = jumps[:, measured], peer_jumps[measured]
    assert np.median(peer_jumps) > 0.1 * scale                    # a C0 scheme: O(1)
    assert np.max(jumps[-1]) < 1e-3 * np.median(peer_jumps)
    # O(step): every halving of the step shrinks the largest jump (by ~4 for δ²)
    worst = jumps.max(axis=1)
    assert np.all(worst[1:] <= 0.6 * worst[:-1]), worst


def test_the_finite_difference_check_sees_directions_that_are_not_shared(random_mesh_data):
    """Control: the same measurement on a spline whose triangles each use their own edge
    directions (rotated by a random angle per triangle, so the two triangles at an edge
    disagree) shows O(1) jumps; the check above would fail for such a spline."""
    tri, f, g, (along, normal, height, minus, plus) = random_mesh_data
    broken = RSDInterpolator(tri.points, f, g, triangles=tri.simplices)
    corners = tri.points[broken.triangles]
    rng = np.random.default_rng(6)
    angle = rng.uniform(0.3, 1.0, (len(corners), 1))
    edge = corners[:, [2, 0, 1]] - corners[:, [1, 2, 0]]           # edge opposite vertex k
    rot = np.stack([edge[..., 0] * np.cos(angle) - edge[..., 1] * np.sin(angle),
                    edge[..., 0] * np.sin(angle) + edge[..., 1] * np.cos(angle)], axis=-1)
    u = np.stack([-rot[..., 1], rot[..., 0]], axis=-1)
    G, _ = rsd.barycentric_gradients(corners)
    broken.coefficients = rsd.triangle_coefficients(
        corners, f[broken.triangles], g[broken.triangles], u, G)
    jumps = normal_derivative_jumps(broken, tri, along, normal, height, minus, plus, STEPS[-1])
    assert np.nanmedian(jumps) > 0.01 * np.abs(g).max()
