"""How far `--smooth` can go with vertices at the data points (issue 24 study, 2026-12-03).

Not part of c1mesh: the measurements behind RESULTS.md "Limits of the shipped smoothing fit".
Each runs on benchmarks.heldout's splits (10% held out, seed s) and scores held-out RMS
against the thin-plate RBF peer of the same split, over the points both cover.

    python -m benchmarks.smoothing_limits ceiling [SEED]           # synthetic terrain only
    python -m benchmarks.smoothing_limits sweep DATASET SEED S...  # fixed strengths vs auto
    python -m benchmarks.smoothing_limits blocks B... [--seeds 5]  # CV block sides (spacings)
    python -m benchmarks.smoothing_limits gradients DATASET SEED   # auto values, LS gradients
    python -m benchmarks.smoothing_limits gradient-data DATASET SEED W...  # LS gradients as data
    python -m benchmarks.smoothing_limits gradient-data all W... [--seeds 5]
    python -m benchmarks.smoothing_limits loess DATASET SEED       # local quadratic regression
    python -m benchmarks.smoothing_limits spacing DATASET SEED F... # --spacing F mean spacings
    python -m benchmarks.smoothing_limits grid DATASET LOW [--seeds 5]  # CV grid from 10^LOW

* ceiling: the RSD spline of the *exact* heights and gradients at the training vertices
  (the pipeline's trimmed triangulation and edge directions), scored against the true
  heights: the best any vertex data that sample the surface can do;
* sweep: `smooth=S` for each S, and auto;
* blocks: auto with smoothing.CV_BLOCK set to each B, on every heldout dataset;
* gradients: auto's values with gradients re-fitted to them by
  c1mesh.stages.height_gradients (k = 16, 24, 40), instead of the fit's own;
* gradient-data: auto refitted with the heights' least-squares gradients
  (height_gradients, the pipeline's 24 neighbours) as gradient data of weight W (the
  weight file normals get, smoothing.FILE_NORMALS_WEIGHT, is 1);
* loess: no smoothing fit; each vertex's height and gradient from a weighted local
  quadratic (with a constant term) over its k nearest vertices' heights, k = 12 ... 100;
* spacing: auto with --spacing F × the mean spacing (vertices thinned to cells, every
  training point as data);
* grid: auto with the coarse search grid (smoothing.GRID, from 10^-3) started at 10^LOW
  instead, against the shipped grid: whether the grid's floor cuts off a better strength.
DATASET: "synth" or a LAS/LAZ name in data_samples/. The studies fit with the pipeline as
it is; RESULTS.md's numbers of all but gradient-data are from 90e40b1, before the heights'
gradients entered the fit as data (gradient-data's baseline turns them off).
"""
from __future__ import annotations

import argparse

import numpy as np

from benchmarks import heldout as H


class Split:
    """One seed's split of a dataset, the shipped auto model's frame and the RBF peer."""

    def __init__(self, data: "H.Dataset", seed: int, **options):
        import c1mesh.stages.smoothing as sm

        self.data, self.seed = data, seed
        test = H.held_out(len(data.points), seed)
        self.train, held = data.points[~test], data.points[test]
        captured, shipped = {}, sm.smooth_fit

        def capture(points, triangles, data, control, **kw):
            fit = shipped(points, triangles, data, control, **kw)
            captured.update(points=np.array(points), triangles=np.array(triangles), fit=fit,
                            heights=np.array(data.values), directions=kw.get("directions"), data=data,
                            control=control)
            return fit

        sm.smooth_fit = capture
        try:
            self.model = H.c1mesh_model(self.train, smooth="auto", **options)
        finally:
            sm.smooth_fit = shipped
        self.captured = captured
        self.frame = self.model.frame
        local = self.frame.to_local(held)
        self.query, self.height = local[:, :2], local[:, 2]
        self.rbf = H.rbf_tps(self.frame.to_local(self.train), self.query, np.random.default_rng(1000 + seed))[0]

    def true_heights(self, predicted: np.ndarray) -> np.ndarray | None:
        if self.data.truth is None:
            return None
        return H.true_local_heights(self.frame, self.query, self.data.truth, predicted)

    def table(self, predictions: dict[str, np.ndarray]) -> list[str]:
        """Held-out RMS (and true-height RMS) of each prediction and of the RBF, over the
        query points every one covers, with the ratio to the RBF's (kept in self.ratios)."""
        ok = np.isfinite(self.rbf) & np.all([np.isfinite(p) for p in predictions.values()], axis=0)
        unit = self.data.unit

        def rms(p):
            return float(np.sqrt(np.mean((p - self.height)[ok] ** 2)) * unit)

        def true_rms(p):
            truth = self.true_heights(p)
            return "" if truth is None else f", true {np.sqrt(np.mean((p - truth)[ok] ** 2)) * unit:.5f}"

        base = rms(self.rbf)
        self.ratios = [rms(p) / base for p in predictions.values()]
        lines = [f"{self.data.name}, seed {self.seed}: {ok.sum():,} points scored; RBF {base:.5f}{true_rms(self.rbf)}"]
        lines += [f"  {name:34s} {rms(p):.5f} ({rms(p) / base:.3f} of the RBF){true_rms(p)}"
                  for name, p in predictions.items()]
        return lines


def dataset(name: str) -> "H.Dataset":
    return H.synthetic() if name == "synth" else H.lidar_ground(H.SAMPLES / name, name)


def ceiling(seed: int) -> list[str]:
    from c1mesh.engine.interpolator import RSDInterpolator

    split = Split(H.synthetic(), seed)
    points, triangles = split.captured["points"], split.captured["triangles"]

    def truth(uv):
        return H.true_local_heights(split.frame, uv, split.data.truth, np.zeros(len(uv)))

    step = 1e-4
    gradients = np.column_stack([(truth(points + [step, 0]) - truth(points - [step, 0])) / (2 * step),
                                 (truth(points + [0, step]) - truth(points - [0, step])) / (2 * step)])
    exact = RSDInterpolator(points, truth(points), gradients, triangles,
                            directions=split.captured["directions"])(split.query)
    return split.table({"RSD of the exact vertex data": exact, "shipped auto": split.model.interp(split.query)})


def sweep(name: str, seed: int, strengths: list[float]) -> list[str]:
    split = Split(dataset(name), seed)
    predictions = {f"auto (s = {split.model.smoothing.strength:.3g})": split.model.interp(split.query)}
    for s in strengths:
        predictions[f"s = {s:g}"] = H.c1mesh_model(split.train, smooth=s).interp(split.query)
    return split.table(predictions)


def blocks(sides: list[float], seeds: int) -> list[str]:
    import c1mesh.stages.smoothing as sm

    shipped, lines = sm.CV_BLOCK, []
    for data in H.datasets():
        ratios = {side: [] for side in sides}
        for seed in range(seeds):
            split = Split(data, seed)
            predictions = {}
            try:
                for side in sides:
                    sm.CV_BLOCK = side
                    model = H.c1mesh_model(split.train, smooth="auto")
                    predictions[f"blocks {side:g} h (s = {model.smoothing.strength:.3g})"] = model.interp(split.query)
            finally:
                sm.CV_BLOCK = shipped
            lines += split.table(predictions)
            for side, ratio in zip(sides, split.ratios):
                ratios[side].append(ratio)
        lines.append(f"{data.name}: mean ratio to the RBF over {seeds} seeds: "
                     + ", ".join(f"blocks {side:g} h {np.mean(r):.3f}" for side, r in ratios.items()))
        print("\n".join(lines[-1:]), flush=True)
    return lines


def gradients(name: str, seed: int) -> list[str]:
    from c1mesh.engine.interpolator import RSDInterpolator
    from c1mesh.stages.height_gradients import height_gradients

    split = Split(dataset(name), seed)
    c = split.captured
    predictions = {"shipped auto": split.model.interp(split.query)}
    for k in (16, 24, 40):
        refit = height_gradients(c["points"], c["fit"].values, k=k)
        predictions[f"auto values, LS gradients k = {k}"] = RSDInterpolator(
            c["points"], c["fit"].values, refit, c["triangles"], directions=c["directions"])(split.query)
    return split.table(predictions)


def gradient_data(name: str, seed: int, weights: list[float]) -> list[str]:
    """auto refitted with the heights' own least-squares gradients as gradient data."""
    return _gradient_data(_heights_only_split(dataset(name), seed), weights)


def _heights_only_split(data, seed: int) -> Split:
    """The Split of an auto fit without gradient data (HEIGHT_GRADIENTS_WEIGHT 0)."""
    import c1mesh.stages.smoothing as sm

    shipped, sm.HEIGHT_GRADIENTS_WEIGHT = sm.HEIGHT_GRADIENTS_WEIGHT, 0.0
    try:
        return Split(data, seed)
    finally:
        sm.HEIGHT_GRADIENTS_WEIGHT = shipped


def gradient_data_all(weights: list[float], seeds: int) -> list[str]:
    """`gradient_data` on every heldout dataset and seeds 0 .. seeds-1, with the mean
    ratio to the RBF of each weight and of the shipped fit."""
    lines = []
    for data in H.datasets():
        ratios = []
        for seed in range(seeds):
            split = _heights_only_split(data, seed)
            lines += _gradient_data(split, weights)
            ratios.append(split.ratios)
        mean = np.mean(ratios, axis=0)
        lines.append(f"{data.name}: mean ratio to the RBF over {seeds} seeds: heights only {mean[0]:.4f}, "
                     + ", ".join(f"weight {w:g} {m:.4f}" for w, m in zip(weights, mean[1:])))
        print(lines[-1], flush=True)
    return lines


def _gradient_data(split: Split, weights: list[float]) -> list[str]:
    import c1mesh.stages.smoothing as sm
    from c1mesh.engine.interpolator import RSDInterpolator
    from c1mesh.stages.height_gradients import height_gradients, height_neighbours

    c = split.captured
    gradients = height_gradients(c["points"], c["heights"], k=height_neighbours(16))
    predictions = {"auto, heights only": split.model.interp(split.query)}
    for weight in weights:
        fit = sm.smooth_fit(c["points"], c["triangles"], c["data"], c["control"], directions=c["directions"],
                            prior=sm.GradientPrior(gradients, weight))
        predictions[f"LS gradients as data, weight {weight:g} (s = {fit.strength:.3g})"] = RSDInterpolator(
            c["points"], fit.values, fit.gradients, c["triangles"], directions=c["directions"])(split.query)
    return split.table(predictions)


def _local_quadratic(xy: np.ndarray, z: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(values (n,), gradients (n, 2)): at each point, the weighted least-squares quadratic
    with a constant term over its k nearest points (itself included), weights as
    height_gradients' (1 / (1 + d² / r²), r the median neighbour distance)."""
    from scipy.spatial import cKDTree

    index = cKDTree(xy).query(xy, k=k, workers=-1)[1]
    ux, uy = xy[index, 0] - xy[:, 0, None], xy[index, 1] - xy[:, 1, None]
    d2 = ux * ux + uy * uy
    r2 = np.median(d2, axis=1)
    r2[r2 <= 0] = 1.0
    r = np.sqrt(r2)
    ux, uy = ux / r[:, None], uy / r[:, None]
    w = 1.0 / (1.0 + d2 / r2[:, None])
    design = np.stack([np.ones_like(ux), ux, uy, 0.5 * ux * ux, ux * uy, 0.5 * uy * uy], -1)
    weighted = (design * w[..., None]).transpose(0, 2, 1)
    normal = weighted @ design
    normal[:, range(6), range(6)] += 1e-9 * np.trace(normal, axis1=1, axis2=2)[:, None]
    coef = np.linalg.solve(normal, weighted @ z[index][..., None])[..., 0]
    return coef[:, 0], coef[:, 1:3] / r[:, None]


def loess(name: str, seed: int) -> list[str]:
    from c1mesh.engine.interpolator import RSDInterpolator

    split = Split(dataset(name), seed)
    c = split.captured
    predictions = {"shipped auto": split.model.interp(split.query)}
    for k in (12, 24, 40, 64, 100):
        values, grads = _local_quadratic(c["points"], c["heights"], k)
        predictions[f"local quadratic k = {k}"] = RSDInterpolator(
            c["points"], values, grads, c["triangles"], directions=c["directions"])(split.query)
    return split.table(predictions)


def spacing(name: str, seed: int, factors: list[float]) -> list[str]:
    split = Split(dataset(name), seed)
    h = H.mean_spacing(split.frame.to_local(split.train)[:, :2])
    predictions = {"shipped auto": split.model.interp(split.query)}
    for factor in factors:
        model = H.c1mesh_model(split.train, smooth="auto", spacing=factor * h)
        held = split.frame.to_world(np.column_stack([split.query, split.height]))
        predictions[f"auto, --spacing {factor:g} h"] = model.interp(model.frame.to_local(held)[:, :2])
    return split.table(predictions)


def grid(name: str, low: int, seeds: int) -> list[str]:
    import c1mesh.stages.smoothing as sm

    shipped, lines, ratios = sm.GRID, [], []
    data = dataset(name)
    for seed in range(seeds):
        split = Split(data, seed)
        sm.GRID = tuple(float(e) for e in range(low, int(shipped[-1]) + 1))
        try:
            model = H.c1mesh_model(split.train, smooth="auto")
        finally:
            sm.GRID = shipped
        lines += split.table({f"shipped grid (s = {split.model.smoothing.strength:.3g})": split.model.interp(split.query),
                              f"grid from 1e{low} (s = {model.smoothing.strength:.3g})": model.interp(split.query)})
        ratios.append(split.ratios)
    mean = np.mean(ratios, axis=0)
    lines.append(f"{data.name}: mean ratio to the RBF over {seeds} seeds: shipped grid {mean[0]:.4f}, "
                 f"grid from 1e{low} {mean[1]:.4f}")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study", choices=("ceiling", "sweep", "blocks", "gradients", "gradient-data", "loess",
                                          "spacing", "grid"))
    parser.add_argument("args", nargs="*")
    parser.add_argument("--seeds", type=int, default=5)
    args = parser.parse_args()
    if args.study == "ceiling":
        lines = ceiling(int(args.args[0]) if args.args else 0)
    elif args.study == "sweep":
        lines = sweep(args.args[0], int(args.args[1]), [float(s) for s in args.args[2:]])
    elif args.study == "blocks":
        lines = blocks([float(s) for s in args.args], args.seeds)
    elif args.study == "gradients":
        lines = gradients(args.args[0], int(args.args[1]))
    elif args.study == "gradient-data" and args.args[0] == "all":
        lines = gradient_data_all([float(w) for w in args.args[1:]], args.seeds)
    elif args.study == "gradient-data":
        lines = gradient_data(args.args[0], int(args.args[1]), [float(w) for w in args.args[2:]])
    elif args.study == "loess":
        lines = loess(args.args[0], int(args.args[1]))
    elif args.study == "grid":
        lines = grid(args.args[0], int(args.args[1]), args.seeds)
    else:
        lines = spacing(args.args[0], int(args.args[1]), [float(f) for f in args.args[2:]])
    print("\n".join(lines))


if __name__ == "__main__":
    main()
