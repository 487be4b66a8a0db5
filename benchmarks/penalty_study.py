"""Why `--smooth auto` trails the thin-plate RBF, and a penalty that does not (issue 24 study).

Not part of c1mesh: a reproducible measurement behind RESULTS.md "Smoothing penalty study".
It compares, on one held-out split of a benchmarks.heldout dataset:

* ``own``: smooth_fit as shipped, the RSD spline's own thin-plate energy;
* ``discrete``: a discrete thin-plate penalty on the same vertex data u = (f, ∇f),
  ∫ |∇ g_P1|² (g_P1 the piecewise-linear interpolant of the vertex gradients, exact for
  quadratics) + β Σ_edges (f_j − f_i − ½ (g_i + g_j)·d_ij)² / |d_ij|² (zero for quadratics),
  in the same normalised units and the same CV machinery (it replaces assemble_energy);
* each on the fit's trimmed triangulation (``coarse``) and on its midpoint subdivision
  (``refined``: the data stay at the original vertices, the edge midpoints get weight 0).

    python -m benchmarks.penalty_study synth 0 own:coarse:auto discrete:refined:auto
    python -m benchmarks.penalty_study autzen_trim.laz 0 discrete:refined:0.3

The RBF row is benchmarks.heldout's peer on the same split.
"""
from __future__ import annotations

import argparse

import numpy as np
import scipy.sparse as sp

from benchmarks import heldout as H

BETA = 10.0
"""Weight of the edge consistency term (held-out best of 1, 3, 10, 30, 100 on the refined
mesh: 10 and 30 tie on Autzen, 10 best on the synthetic terrain)."""


def discrete_penalty(points: np.ndarray, triangles: np.ndarray, beta: float = BETA) -> sp.csr_matrix:
    """(3N, 3N) CSR in smoothing_system's interleaved layout (f, ∂x f, ∂y f per vertex)."""
    from c1mesh.engine import rsd
    from c1mesh.engine.topology import edge_table

    n = points.shape[0]
    tri = np.asarray(triangles, dtype=np.int64)
    G, det = rsd.barycentric_gradients(points[tri])
    stiff = np.einsum("tid,tjd->tij", G, G) * (0.5 * np.abs(det))[:, None, None]
    rows = [np.broadcast_to(3 * tri[:, :, None] + c, stiff.shape).ravel() for c in (1, 2)]
    cols = [np.broadcast_to(3 * tri[:, None, :] + c, stiff.shape).ravel() for c in (1, 2)]
    R = sp.coo_matrix((np.concatenate([stiff.ravel()] * 2), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(3 * n, 3 * n)).tocsr()
    e = edge_table(tri, n).edges
    d = points[e[:, 1]] - points[e[:, 0]]
    m = e.shape[0]
    cols = np.stack([3 * e[:, 1], 3 * e[:, 0], 3 * e[:, 0] + 1, 3 * e[:, 0] + 2,
                     3 * e[:, 1] + 1, 3 * e[:, 1] + 2], 1).ravel()
    vals = np.stack([np.ones(m), -np.ones(m), -0.5 * d[:, 0], -0.5 * d[:, 1],
                     -0.5 * d[:, 0], -0.5 * d[:, 1]], 1).ravel()
    C = sp.csr_matrix((vals, (np.repeat(np.arange(m), 6), cols)), shape=(m, 3 * n))
    return (R + C.T @ sp.diags(beta / (d**2).sum(1)) @ C).tocsr()


def midpoint_refine(points: np.ndarray, triangles: np.ndarray):
    """(points + edge midpoints, 4 T triangles): every triangle split at its edge midpoints."""
    from c1mesh.engine.topology import edge_table

    table = edge_table(triangles, points.shape[0])
    mid = 0.5 * (points[table.edges[:, 0]] + points[table.edges[:, 1]])
    te = table.tri_edge + points.shape[0]           # edge opposite corner k, as a new vertex
    a, b, c = np.asarray(triangles).T
    ab, bc, ca = te[:, 2], te[:, 0], te[:, 1]
    new = np.concatenate([np.stack(x, 1) for x in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
    return np.vstack([points, mid]), new


def run(name: str, seed: int, configs: list[str]) -> None:
    import c1mesh.stages.smoothing as sm
    from c1mesh.engine.interpolator import RSDInterpolator

    data = H.synthetic() if name == "synth" else H.lidar_ground(H.SAMPLES / name, name)
    test = H.held_out(len(data.points), seed)
    train, held = data.points[~test], data.points[test]
    captured, shipped = {}, sm.smooth_fit

    def capture(points, triangles, data, *args, **kw):
        captured.update(p=np.array(points), t=np.array(triangles), z=np.array(data.values), h=data.spacing)
        return shipped(points, triangles, data, *args, **kw)

    sm.smooth_fit = capture
    model = H.c1mesh_model(train, smooth=0.03)      # only for its frame and trimmed triangulation
    sm.smooth_fit = shipped
    local = model.frame.to_local(held)
    q, z = local[:, :2], local[:, 2]
    rbf, note = H.rbf_tps(model.frame.to_local(train), q, np.random.default_rng(1000 + seed))
    covered = np.isfinite(model.interp(q)) & np.isfinite(rbf)

    def rms(pred):
        return float(np.sqrt(np.mean((pred - z)[covered] ** 2)) * data.unit)

    def true_rms(pred):
        if data.truth is None:
            return ""
        t = H.true_local_heights(model.frame, q, data.truth, pred)
        return f"  true {np.sqrt(np.mean((pred - t)[covered] ** 2)) * data.unit:.5f}"

    print(f"{data.name}, seed {seed}: RBF TPS ({note}) held-out {rms(rbf):.5f}{true_rms(rbf)}")
    own_energy = sm.assemble_energy
    P, T = captured["p"], captured["t"]
    for config in configs:
        penalty, mesh, strength = config.split(":")
        sm.assemble_energy = (own_energy if penalty == "own"
                              else (lambda p, t, d, s: discrete_penalty(p, t)))
        pts, tris, z_fit, w = P, T, captured["z"], None
        if mesh == "refined":
            pts, tris = midpoint_refine(P, T)
            extra = pts.shape[0] - P.shape[0]
            z_fit = np.concatenate([captured["z"], np.zeros(extra)])
            w = np.concatenate([np.ones(P.shape[0]), np.zeros(extra)])
        fit = sm.smooth_fit(pts, tris, sm.SmoothingData(z_fit, captured["h"], weights=w),
                            sm.SmoothingControl(strength if strength == "auto" else float(strength)))
        sm.assemble_energy = own_energy
        pred = RSDInterpolator(pts, fit.values, fit.gradients, tris)(q)
        print(f"  {config:28s} s {fit.strength:8.3g}  held-out {rms(pred):.5f} "
              f"({rms(pred) / rms(rbf):.3f} of RBF){true_rms(pred)}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", help="synth, or a LAS/LAZ name in data_samples/")
    parser.add_argument("seed", type=int)
    parser.add_argument("configs", nargs="+", help="PENALTY:MESH:STRENGTH, e.g. discrete:refined:auto")
    parser.add_argument("--search-vertices", type=int, default=None,
                        help="smoothing.SEARCH_VERTICES for this run (above it the CV uses windows)")
    args = parser.parse_args()
    if args.search_vertices:
        import c1mesh.stages.smoothing as sm
        sm.SEARCH_VERTICES = args.search_vertices
    run(args.dataset, args.seed, args.configs)


if __name__ == "__main__":
    main()
