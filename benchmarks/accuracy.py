"""Accuracy: convergence of values and gradients, and a real terrain with held-out points.

Analytic part: N = 100 … 25,600 points (×4, so h halves per step) in the unit square, with
corners and points on the edges so the hull is the whole square; exact values and
gradients; errors on a fixed grid of cell centres (all interior; 200×200 in the full run). One Delaunay
triangulation per N is shared by every method:
  sextic, quintic   c1mesh RSDInterpolator with exact gradients (its own `gradient`);
  rHCT              matplotlib CubicTriInterpolator(kind='user', exact dz), `gradient()`;
  CT                scipy CloughTocher2DInterpolator, which estimates its own vertex
                    gradients from values only; its gradient by central differences
                    (step 1e-6), as scipy has no gradient method.
Observed order = log2(error(N) / error(4N)), i.e. per halving of h.

Terrain part: matplotlib's jacksboro_fault_dem.npz (metres, 3 arc-second grid, spacing
taken from its dx/dy keys), subsampled. The methods see the training points only: sextic
and rHCT get gradients fitted to the training heights as `c1mesh fit` does for a scan
without normals and height axis z (c1mesh.stages.height_gradients, a weighted local quadratic
over 24 neighbours), CT estimates its own from the training values. Errors at all held-out grid points inside
the hull; the gradient reference there is central differences on the full grid.
"""
from __future__ import annotations

import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.tri as mtri  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib import cbook  # noqa: E402
from scipy.interpolate import CloughTocher2DInterpolator  # noqa: E402
from scipy.spatial import Delaunay  # noqa: E402

from benchmarks.common import FUNCTIONS, Config, Section  # noqa: E402
from c1mesh import RSDInterpolator  # noqa: E402

METHODS = ("sextic", "quintic", "rHCT", "CT")
FD_STEP = 1e-6
ROUNDOFF = 1e-11


def square_points(n: int, seed: int) -> np.ndarray:
    """n points: 4 corners, ~sqrt(n) random points inside each edge, the rest uniform inside."""
    rng = np.random.default_rng(seed)
    k = max(1, int(round(np.sqrt(n))) - 1)
    t = rng.random((4, k))
    zero, one = np.zeros(k), np.ones(k)
    boundary = np.concatenate([[[0, 0], [1, 0], [0, 1], [1, 1]],
                               np.c_[t[0], zero], np.c_[t[1], one],
                               np.c_[zero, t[2]], np.c_[one, t[3]]])
    return np.concatenate([boundary, rng.random((n - len(boundary), 2))])


def evaluate(method: str, d: Delaunay, z, g, xe) -> tuple[np.ndarray, np.ndarray]:
    """Values (m,) and gradients (m, 2) of one method at points xe, fitted on triangulation d."""
    pts, tri = d.points, d.simplices
    if method in ("sextic", "quintic"):
        I = RSDInterpolator(pts, z, g, triangles=tri, scheme=method)
        return I(xe), I.gradient(xe)
    if method == "rHCT":
        t = mtri.Triangulation(pts[:, 0], pts[:, 1], triangles=tri)
        interp = mtri.CubicTriInterpolator(t, z, kind="user", dz=(g[:, 0], g[:, 1]))
        v = np.ma.filled(interp(xe[:, 0], xe[:, 1]), np.nan)
        gx, gy = (np.ma.filled(a, np.nan) for a in interp.gradient(xe[:, 0], xe[:, 1]))
        return v, np.stack([gx, gy], axis=1)
    ct = CloughTocher2DInterpolator(d, z)
    grad = np.empty((len(xe), 2))
    for axis in range(2):
        step = np.zeros(2)
        step[axis] = FD_STEP
        grad[:, axis] = (ct(xe + step) - ct(xe - step)) / (2 * FD_STEP)
    return ct(xe), grad


def errors(v, gr, z_true, g_true) -> tuple[float, float, float, float]:
    """(value max, value RMS, gradient max, gradient RMS); gradient error is |Δ∇| (Euclidean)."""
    ev = np.abs(v - z_true)
    eg = np.linalg.norm(gr - g_true, axis=1)
    return (float(ev.max()), float(np.sqrt(np.mean(ev ** 2))),
            float(eg.max()), float(np.sqrt(np.mean(eg ** 2))))


def orders(errs: list[float]) -> str:
    out = []
    for a, b in zip(errs, errs[1:]):
        out.append("exact" if max(a, b) < ROUNDOFF else f"{np.log2(a / b):.2f}")
    return ", ".join(out)


def run(cfg: Config) -> Section:
    sec = Section("Accuracy: convergence orders and a real terrain")
    sec.add(__doc__.split("\n\n", 1)[1].strip(), "")
    c = (np.arange(cfg.accuracy_grid) + 0.5) / cfg.accuracy_grid
    xe = np.stack(np.meshgrid(c, c), axis=-1).reshape(-1, 2)
    results, worst = {}, {}                # (function, method) -> [errors per N]; worst angles
    for fname, f in FUNCTIONS.items():
        z_true, g_true = f(xe)
        for n in cfg.accuracy_sizes:
            d = Delaunay(square_points(n, seed=n))
            z, g = f(d.points)
            for m in METHODS:
                v, gr = evaluate(m, d, z, g, xe)
                results.setdefault((fname, m), []).append(errors(v, gr, z_true, g_true))
                if n == cfg.accuracy_sizes[-1]:
                    worst[fname, m] = _angle_at_worst(d, xe, gr, g_true)
    sizes = ", ".join(f"{n:,}" for n in cfg.accuracy_sizes)
    sec.add(f"### Observed orders (N = {sizes}; one entry per halving of h)", "",
            "| function | method | value RMS orders | gradient RMS orders | value max orders | "
            f"value RMS at N={cfg.accuracy_sizes[-1]:,} | "
            f"gradient RMS at N={cfg.accuracy_sizes[-1]:,} |",
            "|---|---|---|---|---|---:|---:|")
    for (fname, m), errs in results.items():
        e = np.array(errs)
        sec.add(f"| {fname} | {m} | {orders(e[:, 1])} | {orders(e[:, 3])} | {orders(e[:, 0])} | "
                f"{e[-1, 1]:.2e} | {e[-1, 3]:.2e} |")
    sec.add("", "'exact' = both errors below 1e-11 (the method reproduces the function).", "",
            *_reading(results, worst, cfg.accuracy_sizes[-1]), "",
            "<details><summary>All errors</summary>", "",
            "| function | method | N | value max | value RMS | gradient max | gradient RMS |",
            "|---|---|---:|---:|---:|---:|---:|")
    for (fname, m), errs in results.items():
        for n, e in zip(cfg.accuracy_sizes, errs):
            sec.add(f"| {fname} | {m} | {n:,} | " + " | ".join(f"{x:.2e}" for x in e) + " |")
    sec.add("", "</details>", "")
    _plot(results, cfg.accuracy_sizes, cfg.out / "accuracy.png")
    sec.add("![accuracy](accuracy.png)", "")
    sec.add(*_terrain(sec, cfg.terrain_crop))
    return sec


def _angle_at_worst(d: Delaunay, xe, gr, g_true) -> float:
    """Smallest angle (degrees) of the triangle holding the largest gradient error."""
    i = int(np.argmax(np.linalg.norm(gr - g_true, axis=1)))
    p = d.points[d.simplices[d.find_simplex(xe[i:i + 1])[0]]]
    angles = []
    for k in range(3):
        a, b = p[(k + 1) % 3] - p[k], p[(k + 2) % 3] - p[k]
        cos = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
        angles.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return float(min(angles))


def _reading(results, worst, n_last) -> list[str]:
    """What the numbers say, computed from this run: mean orders of the last two steps."""
    out = ["**What these numbers say**: order = mean of the last two observed orders over the "
           "three functions ('exact' steps left out); 'worst at' = smallest angle of the triangle "
           f"holding the largest gradient error at N={n_last:,} (distinct values over the "
           "functions, which share one mesh per N).", ""]
    for m in METHODS:
        v, g = [], []
        for fname in FUNCTIONS:
            e = np.array(results[fname, m])
            for col, acc in ((1, v), (3, g)):
                a, b = e[-3:-1, col], e[-2:, col]
                keep = np.maximum(a, b) >= ROUNDOFF
                acc.extend(np.log2(a[keep] / b[keep]))
        fmt = lambda xs: f"{np.mean(xs):.2f}" if xs else "exact"  # noqa: E731
        angles = ", ".join(dict.fromkeys(f"{worst[f, m]:.1f}°" for f in FUNCTIONS))
        out.append(f"- {m}: value order ≈ {fmt(v)}, gradient order ≈ {fmt(g)}; worst at {angles}")
    ratios = []
    for f in FUNCTIONS:
        ours, theirs = results[f, "sextic"][-1][1], results[f, "rHCT"][-1][1]
        ratios.append(f"{f} " + (f"{ours / theirs:.3g}×" if theirs >= ROUNDOFF else "(rHCT exact)"))
    out.append(f"- sextic value RMS / rHCT value RMS at N={n_last:,}: {', '.join(ratios)}.")
    return out


def _plot(results, sizes, path) -> None:
    h = 1 / np.sqrt(np.array(sizes, dtype=float))
    fig, axes = plt.subplots(2, len(FUNCTIONS), figsize=(11, 6), dpi=70, sharex=True)
    for col, fname in enumerate(FUNCTIONS):
        for row, (q, label) in enumerate(((1, "value"), (3, "gradient"))):
            ax = axes[row, col]
            for i, m in enumerate(METHODS):
                e = np.maximum(np.array(results[fname, m]), 1e-16)
                ax.loglog(h, e[:, q], "o-", color=f"C{i}", label=f"{m} RMS", ms=3)
                ax.loglog(h, e[:, q - 1], ":", color=f"C{i}", lw=1)
            ax.set_title(f"{fname}: {label} error", fontsize=9)
            if row == 1:
                ax.set_xlabel("h = 1/sqrt(N)")
    axes[0, 0].legend(fontsize=7, title="solid RMS, dotted max", title_fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def training_gradients(xyz: np.ndarray) -> np.ndarray:
    """Gradients (n, 2) at training points (n, 3) fitted to their heights, as the fit
    pipeline gets them for a scan without normals and height axis z."""
    from c1mesh.stages.height_gradients import height_gradients, height_neighbours
    return height_gradients(xyz[:, :2], xyz[:, 2], k=height_neighbours(16))


def _terrain(sec: Section, crop: int | None = None) -> list[str]:
    """Jacksboro DEM: fit on subsets, errors at held-out grid points (metres)."""
    data = cbook.get_sample_data("jacksboro_fault_dem.npz")
    elev = data["elevation"].astype(float)
    if crop:
        elev = elev[:crop, :crop]
    lat = np.radians((float(data["ymin"]) + float(data["ymax"])) / 2)
    R = 6_371_008.8
    dy = np.radians(abs(float(data["dy"]))) * R
    dx = np.radians(abs(float(data["dx"]))) * R * np.cos(lat)
    rows, cols = elev.shape
    gy, gx = np.gradient(elev, dy, dx)       # reference only: central differences on the full grid
    rr, cc = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    xy = np.stack([cc.ravel() * dx, rr.ravel() * dy], axis=1)
    z, g = elev.ravel(), np.stack([gx.ravel(), gy.ravel()], axis=1)
    on_side = (cc == 0) | (cc == cols - 1), (rr == 0) | (rr == rows - 1)
    border = ((rr % 4 == 0) & on_side[0]) | ((cc % 4 == 0) & on_side[1])
    corners = ((rr == 0) | (rr == rows - 1)) & ((cc == 0) | (cc == cols - 1))
    regular = (rr % 4 == 0) & (cc % 4 == 0)
    rng = np.random.default_rng(4)
    random = rng.random(elev.shape) < 1 / 16
    out = [f"### Real terrain: jacksboro_fault_dem.npz ({rows}×{cols} elevations{', a corner crop' if crop else ''}, metres; "
           f"grid spacing {dx:.1f} m × {dy:.1f} m from dx = dy = {float(data['dx']):.6g}°)", "",
           "Fitting sees the training points only: sextic and rHCT get gradients fitted to the "
           "training heights, as `c1mesh fit` gets them for a scan without normals "
           "(c1mesh.stages.height_gradients, a weighted local quadratic over 24 neighbours); "
           "CT estimates its own gradients from the training values. "
           "Errors at every held-out grid point inside the hull; gradient errors are against "
           "central differences on the full grid (approximate; elevations are whole metres).", "",
           "| fit set | fit points | held out | method | value max (m) | value RMS (m) | "
           "gradient RMS (m/m) |", "|---|---:|---:|---|---:|---:|---:|"]
    for label, mask in (("every 4th row and column", regular),
                        ("random 1/16 of the grid + border every 4th", random | border | corners)):
        fit = mask.ravel()
        d = Delaunay(xy[fit])
        held = np.flatnonzero(~fit)
        held = held[d.find_simplex(xy[held]) >= 0]
        train_g = training_gradients(np.column_stack([xy[fit], z[fit]]))
        fits = {m: evaluate(m, d, z[fit], train_g, xy[held]) for m in ("sextic", "rHCT", "CT")}
        # common points where every method is defined (CT's finite differences are not on the hull)
        ok = np.logical_and.reduce([np.isfinite(v) & np.isfinite(gr).all(axis=1)
                                    for v, gr in fits.values()])
        rms = {}
        for m, (v, gr) in fits.items():
            e = errors(v[ok], gr[ok], z[held][ok], g[held][ok])
            rms[m] = e[1]
            out.append(f"| {label} | {fit.sum():,} | {ok.sum():,} | {m} | {e[0]:.2f} | "
                       f"{e[1]:.3f} | {e[3]:.4f} |")
        sec.headlines.append((f"terrain ({label}): held-out value RMS, rHCT / sextic",
                              f"{rms['rHCT'] / rms['sextic']:.2f}×",
                              "(none set; > 1 = sextic better)", "—"))
    return out + [""]
