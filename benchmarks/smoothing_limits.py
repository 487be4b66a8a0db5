"""How far `--smooth` can go with vertices at the data points (issue 24 study, 2026-12-03).

Not part of c1mesh: the measurements behind RESULTS.md "Limits of the shipped smoothing fit".
Each runs on benchmarks.heldout's splits (10% held out, seed s) and scores held-out RMS
against the thin-plate RBF peer of the same split, over the points both cover.

    python -m benchmarks.smoothing_limits ceiling [SEED]           # synthetic terrain only
    python -m benchmarks.smoothing_limits sweep DATASET SEED S...  # fixed strengths vs auto
    python -m benchmarks.smoothing_limits blocks B... [--seeds 5]  # CV block sides (spacings)
    python -m benchmarks.smoothing_limits gradients DATASET SEED   # auto values, LS gradients

* ceiling: the RSD spline of the *exact* heights and gradients at the training vertices
  (the pipeline's trimmed triangulation and edge directions), scored against the true
  heights: the best any vertex data that sample the surface can do;
* sweep: `smooth=S` for each S, and auto;
* blocks: auto with smoothing.CV_BLOCK set to each B, on every heldout dataset;
* gradients: auto's values with gradients re-fitted to them by
  c1mesh.stages.height_gradients (k = 16, 24, 40), instead of the fit's own.
DATASET: "synth" or a LAS/LAZ name in data_samples/.
"""
from __future__ import annotations

import argparse

import numpy as np

from benchmarks import heldout as H


class Split:
    """One seed's split of a dataset, the shipped auto model's frame and the RBF peer."""

    def __init__(self, data: "H.Dataset", seed: int, **options):
        import c1mesh.pipeline.steps as steps

        self.data, self.seed = data, seed
        test = H.held_out(len(data.points), seed)
        self.train, held = data.points[~test], data.points[test]
        captured, shipped = {}, steps.smooth_fit

        def capture(points, triangles, values, **kw):
            fit = shipped(points, triangles, values, **kw)
            captured.update(points=np.array(points), triangles=np.array(triangles), fit=fit,
                            directions=kw.get("directions"))
            return fit

        steps.smooth_fit = capture
        try:
            self.model = H.c1mesh_model(self.train, smooth="auto", **options)
        finally:
            steps.smooth_fit = shipped
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study", choices=("ceiling", "sweep", "blocks", "gradients"))
    parser.add_argument("args", nargs="*")
    parser.add_argument("--seeds", type=int, default=5)
    args = parser.parse_args()
    if args.study == "ceiling":
        lines = ceiling(int(args.args[0]) if args.args else 0)
    elif args.study == "sweep":
        lines = sweep(args.args[0], int(args.args[1]), [float(s) for s in args.args[2:]])
    elif args.study == "blocks":
        lines = blocks([float(s) for s in args.args], args.seeds)
    else:
        lines = gradients(args.args[0], int(args.args[1]))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
