"""Held-out accuracy on noisy ground: c1mesh against smoothing gridders (issue 24).

    python -m benchmarks.heldout [--quick] [--seeds 5] [--write]

For every dataset, 10% of the points are held out at random (seeds 0, 1, ...; the same
split for every method), each method is fitted to the other 90% and evaluated at the
held-out (x, y); the table shows the RMS of (prediction − held-out height) in metres, its
ratio to the linear TIN's, and the seconds of fit + evaluation (mean over seeds).

Heights are measured along the height axis e3 of the frame c1mesh chooses for the training
points (c1mesh.stages.frame.choose_frame; LiDAR ground is tilted by 1-3° from z there): every
peer is fitted and evaluated in that frame's local (x, y, height) coordinates, and c1mesh's
spline is evaluated at the held-out points' local (x, y) through the Python API
(c1mesh.pipeline.driver.build_surface, normals estimated as `c1mesh fit` does). Scores are over
the held-out points every method covers: inside the training points' convex hull (TIN,
Clough–Tocher) and inside c1mesh's trimmed triangulation (its --max-edge auto trim).

Methods:
  linear TIN        scipy LinearNDInterpolator (the reference of every ratio);
  Clough–Tocher     scipy CloughTocher2DInterpolator (C1 cubic, estimated gradients; exact);
  GMT surface       the `gmt` binary: blockmedian at the nearest-neighbour spacing s (the
                    median distance from a training point to its nearest neighbour), surface
                    -I s -T0.25 and -T0.35 (continuous-curvature splines in tension), grdtrack
                    -nc (bicubic) at the held-out points; timed as the three processes. Issue
                    38: the hull-area spacing sqrt(area / n) used before is 1.5-2x coarser and
                    put GMT behind the TIN; s gives GMT its best setting;
  RBF TPS           scipy RBFInterpolator(kernel="thin_plate_spline", neighbors=50), smoothing
                    chosen on a validation split (10% of the training points) from {0} ∪
                    10^-5 … 10^3, refitted on all training points;
  verde Spline      verde.Spline (biharmonic Green's functions, dense n×n), damping chosen on
                    the same validation split from 10^-8, 10^-6, 10^-4, 10^-2; only up to
                    VERDE_MAX training points (its matrix is n² doubles);
  c1mesh exact      FitOptions(smooth="off") (an interpolating C1 spline, overshoot limiter on);
  c1mesh overshoot=off   FitOptions(overshoot="off");
  c1mesh smooth=auto     FitOptions(smooth="auto"), when this build's FitOptions has that field;
  c1mesh default         FitOptions(smooth="default"): what `c1mesh fit` does without
                         --smooth, here (normals estimated) issue 38's lattice route,
                         --smooth auto --spacing auto: the vertices the nodes of a lattice at
                         D = sqrt(box area / n) of the training points (2 significant
                         digits). Its held-out RMS moves with where the lattice falls on
                         the points: 1.5 % over six sub-cell shifts on autzen_trim ground
                         (docs/smoothing.md, "The least strength against the lattice's
                         position"); the row is today's position.
A peer that is not installed is skipped and the table says so (benchmarks/install-peers.sh
installs GMT and verde). The synthetic terrain (analytic heights + 2 cm Gaussian noise;
50,000 points over 100 m, and 5,000 over its 31.6 m corner at the same density, small enough
for verde) also gets the RMS against its true heights (along e3, by Newton's method on the
analytic surface) and the noise floor, the RMS of the noise at the scored points. Seconds are
wall time on a shared machine, for orientation only.
"""
from __future__ import annotations

import argparse
import dataclasses
import gc
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

from benchmarks.common import ROOT, Config, Section, write_section

SAMPLES = ROOT / "data_samples"
REAL = Path("/work/shared/data/real")
"""The shared real scans (see its README.md); a LAS/LAZ there that is a byte copy of one in
data_samples/ is not measured twice."""
TITLE = "Held-out accuracy on noisy ground"
HOLD = 0.10
SYNTH_N, SYNTH_NOISE, SYNTH_SIZE = 50_000, 0.02, 100.0
VERDE_MAX = 5_000
"""Largest training set verde.Spline is given: its Jacobian is n² doubles and its fit O(n³)
(measured here: 4,500 training points, 5 fits of the damping search, about a minute)."""
SMALL_N = 5_000
SMALL_SIZE = round(SYNTH_SIZE * (SMALL_N / SYNTH_N) ** 0.5, 1)
"""The small synthetic set, the one every peer (verde too) is measured on: SMALL_N points on
the corner SMALL_SIZE × SMALL_SIZE m of the same terrain, at the large set's density."""
RBF_SMOOTHING = (0.0, *(10.0 ** np.arange(-5, 4)))
VERDE_DAMPING = (1e-8, 1e-6, 1e-4, 1e-2)
TENSIONS = (0.25, 0.35)
RBF = "RBF TPS (neighbors=50)"
"""The best peer measured so far (issue 38's next mark): every table gives the ratio to it."""


# ----------------------------------------------------------------------------- datasets
@dataclasses.dataclass
class Dataset:
    """points: (N, 3) world coordinates; unit: metres per coordinate unit; truth: for an
    analytic set, f(xy) -> (heights (n,), gradients (n, 2)) of the noise-free surface, and
    noise (N,) the noise added to its heights (else None)."""

    name: str
    points: np.ndarray
    unit: float = 1.0
    truth: Callable | None = None
    noise: np.ndarray | None = None

    def subsample(self, count: int | None, seed: int = 0) -> "Dataset":
        if count is None or len(self.points) <= count:
            return self
        keep = np.sort(np.random.default_rng(seed).choice(len(self.points), count, replace=False))
        return dataclasses.replace(self, points=self.points[keep],
                                   noise=None if self.noise is None else self.noise[keep])


BUMPS = ((22.0, 70.0, 1.2, 4.0), (60.0, 30.0, -0.8, 3.0), (75.0, 80.0, 0.6, 2.0),
         (40.0, 45.0, 0.9, 6.0), (85.0, 15.0, 0.5, 2.5))
"""Gaussian hills (centre x, centre y, amplitude, sigma) in metres."""


def synthetic_height(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Heights (n,) and gradients (n, 2), metres, of a 100 m terrain: rolling hills, a
    0.3 m ripple of 9 m wavelength across x + 2y, a 2% tilt and BUMPS."""
    x, y = xy[:, 0], xy[:, 1]
    w = 2 * np.pi / 9.0
    z = 3 * np.sin(x / 10) * np.cos(y / 15) + 0.02 * x + 0.3 * np.sin(w * (x + 2 * y))
    gx = 0.3 * np.cos(x / 10) * np.cos(y / 15) + 0.02 + 0.3 * w * np.cos(w * (x + 2 * y))
    gy = -0.2 * np.sin(x / 10) * np.sin(y / 15) + 0.6 * w * np.cos(w * (x + 2 * y))
    for cx, cy, a, s in BUMPS:
        e = a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
        z = z + e
        gx = gx - e * (x - cx) / (s * s)
        gy = gy - e * (y - cy) / (s * s)
    return z, np.column_stack([gx, gy])


def synthetic(n: int = SYNTH_N, noise: float = SYNTH_NOISE, seed: int = 7,
              size: float = SYNTH_SIZE, name: str | None = None) -> Dataset:
    """n uniform random points over a size × size m square on `synthetic_height`, plus
    Gaussian noise of standard deviation `noise` metres on the heights."""
    rng = np.random.default_rng(seed)
    xy = rng.random((n, 2)) * size
    eps = rng.normal(0.0, noise, n) if noise else np.zeros(n)
    z = synthetic_height(xy)[0] + eps
    label = name or f"synthetic terrain, {size:g} m, {noise * 100:g} cm noise"
    return Dataset(label, np.column_stack([xy, z]), 1.0, synthetic_height, eps)


def crs_unit(wkt: str | None) -> float:
    """Metres per unit of a CRS's coordinates: the last LENGTHUNIT of its WKT (1: none)."""
    found = re.findall(r'LENGTHUNIT\["[^"]*",\s*([0-9.eE+-]+)', wkt or "")
    return float(found[-1]) if found else 1.0


def lidar_ground(path: Path, name: str) -> Dataset:
    """The ground (class 2) of a LAS/LAZ, or every point when it is not classified."""
    from c1mesh.core.errors import InputError
    from c1mesh.pipeline.driver import FitOptions, load_cloud

    try:
        cloud = load_cloud(path, FitOptions(classes=(2,)))
        label = f"{name} ground (class 2)"
    except InputError:
        cloud = load_cloud(path, FitOptions())
        label = f"{name} (all points: no class 2)"
    points = cloud.points[np.isfinite(cloud.points).all(axis=1)]
    return Dataset(label, points, crs_unit(cloud.crs))


def datasets() -> list[Dataset]:
    """The two LiDAR samples, the LAS/LAZ in REAL that are not copies of them, the synthetic."""
    import hashlib

    files = [SAMPLES / "autzen_trim.laz", SAMPLES / "4_6_crop.las"]
    seen = {hashlib.sha256(f.read_bytes()).hexdigest() for f in files}
    for f in sorted(REAL.glob("*.la[sz]")) if REAL.is_dir() else ():
        digest = hashlib.sha256(f.read_bytes()).hexdigest()
        if digest not in seen:
            seen.add(digest)
            files.append(f)
    return ([lidar_ground(f, f.name) for f in files]
            + [synthetic(), synthetic(SMALL_N, size=SMALL_SIZE)])


def true_local_heights(frame, uv: np.ndarray, truth: Callable, start: np.ndarray) -> np.ndarray:
    """Heights t (n,) along e3 where the line origin + u e1 + v e2 + t e3 meets the analytic
    surface z = f(x, y): Newton's method on g(t) = z(t) − f(x(t), y(t)) from `start`."""
    base = frame.origin + uv @ frame.axes[:2]
    e3 = frame.axes[2]
    t = np.array(start, dtype=float)
    for _ in range(50):
        p = base + t[:, None] * e3
        f, grad = truth(p[:, :2])
        step = (p[:, 2] - f) / (e3[2] - grad @ e3[:2])
        t -= step
        if np.max(np.abs(step)) < 1e-12 * (1 + np.max(np.abs(t))):
            break
    return t


# ----------------------------------------------------------------------------- methods
# A peer: (train (n, 3) local x, y, height; query (m, 2) local x, y; rng) -> (heights (m,),
# a note such as the parameter it chose, or "").
def tin(train, query, rng):
    from scipy.interpolate import LinearNDInterpolator

    return LinearNDInterpolator(train[:, :2], train[:, 2])(query), ""


def clough_tocher(train, query, rng):
    from scipy.interpolate import CloughTocher2DInterpolator

    return CloughTocher2DInterpolator(train[:, :2], train[:, 2])(query), ""


def validation_split(n: int, rng) -> np.ndarray:
    """(n,) bool: the 10% of the training points that choose a smoothing parameter."""
    return rng.permutation(n) < max(1, int(round(HOLD * n)))


def _choose(train, rng, fit_predict, params):
    """The parameter of `params` with the least RMS on a validation split of `train`."""
    val = validation_split(len(train), rng)
    fit, check = train[~val], train[val]
    scores = []
    for p in params:
        pred = fit_predict(fit, check[:, :2], p)
        ok = np.isfinite(pred)
        scores.append(np.sqrt(np.mean((pred[ok] - check[ok, 2]) ** 2)) if ok.any() else np.inf)
    return params[int(np.argmin(scores))]


def _rbf(train, query, smoothing):
    from scipy.interpolate import RBFInterpolator

    return RBFInterpolator(train[:, :2], train[:, 2], kernel="thin_plate_spline", neighbors=50,
                           smoothing=smoothing)(query)


def rbf_tps(train, query, rng):
    best = _choose(train, rng, _rbf, RBF_SMOOTHING)
    return _rbf(train, query, best), f"smoothing {best:g}"


def verde_status() -> str:
    """'' when verde imports, else why not."""
    try:
        import verde  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - any failure means the peer is absent
        return f"verde is not installed ({type(exc).__name__})"
    return ""


def _verde(train, query, damping):
    import warnings

    import verde

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        spline = verde.Spline(damping=damping).fit((train[:, 0], train[:, 1]), train[:, 2])
        return spline.predict((query[:, 0], query[:, 1]))


def verde_spline(train, query, rng):
    best = _choose(train, rng, _verde, VERDE_DAMPING)
    return _verde(train, query, best), f"damping {best:g}"


def nearest_spacing(xy: np.ndarray) -> float:
    """The median distance from a point of xy (n, 2) to its nearest other point."""
    from scipy.spatial import cKDTree

    return float(np.median(cKDTree(xy).query(xy, k=2)[0][:, 1]))


def mean_spacing(xy: np.ndarray) -> float:
    """sqrt(convex hull area / n): the side of the square each point covers on average."""
    from scipy.spatial import ConvexHull

    return float(np.sqrt(ConvexHull(xy).volume / len(xy)))


def gmt_status() -> str:
    """'' when the `gmt` binary runs, else why not."""
    if shutil.which("gmt") is None:
        return "gmt not found on PATH (benchmarks/install-peers.sh installs it)"
    return ""


def gmt_version() -> str:
    done = subprocess.run(["gmt", "--version"], capture_output=True, text=True)
    return done.stdout.strip()


def gmt_surface(tension: float):
    """blockmedian → surface -T tension → grdtrack -nc, in a temporary folder, at the
    nearest-neighbour spacing of the training points; the grid covers their bounding box
    padded by 2 cells."""

    def run(train, query, rng):
        s = float(f"{nearest_spacing(train[:, :2]):.4g}")
        lo = np.floor(train[:, :2].min(axis=0) / s) * s - 2 * s
        hi = np.ceil(train[:, :2].max(axis=0) / s) * s + 2 * s
        region = f"-R{lo[0]:.17g}/{hi[0]:.17g}/{lo[1]:.17g}/{hi[1]:.17g}"
        spacing = f"-I{s:.17g}"
        with tempfile.TemporaryDirectory(prefix="c1mesh-gmt-") as tmp:
            d = Path(tmp)
            np.savetxt(d / "train.xyz", train, fmt="%.10f")
            np.savetxt(d / "query.xy", query, fmt="%.10f")
            common = dict(cwd=d, check=True, capture_output=True, text=True)
            block = subprocess.run(["gmt", "blockmedian", "train.xyz", region, spacing,
                                    "--FORMAT_FLOAT_OUT=%.12g"], **common).stdout
            (d / "block.xyz").write_text(block)
            subprocess.run(["gmt", "surface", "block.xyz", region, spacing, f"-T{tension}", "-Gs.nc"],
                           **common)
            out = subprocess.run(["gmt", "grdtrack", "query.xy", "-Gs.nc", "-nc", "-N",
                                  "--FORMAT_FLOAT_OUT=%.12g"], **common).stdout
        rows = np.array([line.split() for line in out.splitlines() if line.strip()], dtype=float)
        if rows.shape != (len(query), 3):
            raise RuntimeError(f"grdtrack returned {rows.shape} for {len(query)} queries")
        return rows[:, 2], f"s = {s:.3g}"

    return run


def smooth_status() -> str:
    """'' when this build's FitOptions has a `smooth` field, else the note the row shows."""
    from c1mesh.pipeline.driver import FitOptions

    if "smooth" in {f.name for f in dataclasses.fields(FitOptions)}:
        return ""
    return "c1mesh smooth: not available in this build"


def c1mesh_model(train_world: np.ndarray, **options):
    """c1mesh's SurfaceModel of training points (world, (n, 3)), normals estimated."""
    from c1mesh.core.cloud import PointCloud
    from c1mesh.pipeline.driver import FitOptions, build_surface

    return build_surface(PointCloud(points=train_world), FitOptions(normals="auto", **{"smooth": "off", **options}))


DEFAULT_ROW = "c1mesh default (lattice, --spacing auto)"


def lattice_status() -> str:
    """'' when this build's FitOptions has a `spacing` field (the lattice route), else why not."""
    from c1mesh.pipeline.driver import FitOptions

    if "spacing" in {f.name for f in dataclasses.fields(FitOptions)}:
        return ""
    return "c1mesh --spacing: not available in this build"


def c1mesh_default(train_world: np.ndarray, test_world: np.ndarray):
    """The default's row: (heights along its frame's e3, frame, note "D, s") of the fit
    without --smooth, the lattice route at --spacing auto."""
    model = c1mesh_model(train_world, smooth="default")
    local = model.frame.to_local(test_world)
    return model.interp(local[:, :2]), model.frame, f"D = {model.lattice['spacing']:.3g}, " \
                                                    f"s = {model.smoothing.strength:.3g}"


def c1mesh_method(**options):
    """A c1mesh row: (train_world, test_world) -> (heights along its frame's e3, frame)."""

    def run(train_world, test_world):
        model = c1mesh_model(train_world, **options)
        local = model.frame.to_local(test_world)
        return model.interp(local[:, :2]), model.frame

    return run


def methods(peers: str = "all") -> tuple[list, dict]:
    """[(name, kind, function)] and {name: why skipped}; kind "peer" or "c1mesh".
    peers: "all", or "scipy" (TIN, Clough–Tocher, RBF: the smoke test's)."""
    rows, skipped = [("linear TIN", "peer", tin), ("Clough–Tocher", "peer", clough_tocher)], {}
    if peers == "all":
        why = gmt_status()
        for t in TENSIONS:
            if why:
                skipped[f"GMT surface -T{t}"] = why
            else:
                rows.append((f"GMT surface -T{t}", "peer", gmt_surface(t)))
    rows.append((RBF, "peer", rbf_tps))
    if peers == "all":
        why = verde_status()
        if why:
            skipped["verde Spline"] = why
        else:
            rows.append(("verde Spline", "peer", verde_spline))
    rows += [("c1mesh exact", "c1mesh", c1mesh_method()),
             ("c1mesh overshoot=off", "c1mesh", c1mesh_method(overshoot="off"))]
    why = smooth_status()
    if why:
        skipped["c1mesh smooth=auto"] = why
    else:
        rows.append(("c1mesh smooth=auto", "c1mesh", c1mesh_method(smooth="auto")))
    why = why or lattice_status()
    if why:
        skipped[DEFAULT_ROW] = why
    else:
        rows.append((DEFAULT_ROW, "c1mesh", c1mesh_default))
    return rows, skipped


# ----------------------------------------------------------------------------- the run
def held_out(n: int, seed: int) -> np.ndarray:
    """(n,) bool: exactly round(10% of n) points, chosen by `seed`."""
    return np.random.default_rng(seed).permutation(n) < int(round(HOLD * n))


_WARM: set[str] = set()


def _warm_up(rows) -> None:
    """Run each method once on 400 synthetic points, untimed, so that imports and first-call
    set-up (Qhull, BLAS threads, subprocess caches) are not charged to the first dataset."""
    todo = [r for r in rows if r[0] not in _WARM]
    if not todo:
        return
    pts = synthetic(400, 0.0, seed=99, size=10.0).points
    test = held_out(len(pts), 0)
    frame = c1mesh_model(pts[~test]).frame
    for name, kind, fn in todo:
        if kind == "c1mesh":
            fn(pts[~test], pts[test])
        else:
            fn(frame.to_local(pts[~test]), frame.to_local(pts[test])[:, :2], np.random.default_rng(0))
        _WARM.add(name)


def _timed(fn):
    gc.collect()
    start = time.perf_counter()
    result = fn()
    return result, time.perf_counter() - start


def evaluate(data: Dataset, seeds=(0, 1, 2, 3, 4), peers: str = "all", log=print) -> dict:
    """Every method on every seed's split of `data`. Returns {"rows": {name: {"rms": [...],
    "rms_true": [...], "seconds": [...], "notes": [...]}}, "skipped": {name: why},
    "scored": [...], "held": [...], "noise": [...], "tilt": [...]}; RMS in metres."""
    rows, skipped = methods(peers)
    if len(data.points) * (1 - HOLD) > VERDE_MAX:
        skipped.setdefault("verde Spline", f"{int(len(data.points) * (1 - HOLD)):,} training points > "
                                           f"VERDE_MAX = {VERDE_MAX:,} (dense n² matrix)")
    rows = [r for r in rows if r[0] not in skipped]
    _warm_up(rows)
    out = {"rows": {name: {"rms": [], "rms_true": [], "seconds": [], "notes": []} for name, _, _ in rows},
           "skipped": skipped, "scored": [], "held": [], "noise": [], "tilt": []}
    for seed in seeds:
        test = held_out(len(data.points), seed)
        train_w, test_w = data.points[~test], data.points[test]
        preds, frames = {}, {}
        for name, kind, fn in rows:
            if kind != "c1mesh":
                continue
            fitted, sec = _timed(lambda: fn(train_w, test_w))
            preds[name], frames[name] = fitted[0], fitted[1]
            out["rows"][name]["seconds"].append(sec)
            out["rows"][name]["notes"].append(fitted[2] if len(fitted) > 2 else "")
        frame = frames["c1mesh exact"]
        train_l, test_l = frame.to_local(train_w), frame.to_local(test_w)
        for name, kind, fn in rows:
            if kind == "c1mesh":
                continue
            rng = np.random.default_rng(1000 + seed)
            (pred, note), sec = _timed(lambda: fn(train_l, test_l[:, :2], rng))
            preds[name], frames[name] = np.asarray(pred, dtype=float), frame
            out["rows"][name]["seconds"].append(sec)
            out["rows"][name]["notes"].append(note)
        ok = np.all([np.isfinite(p) for p in preds.values()], axis=0)
        out["scored"].append(int(ok.sum()))
        out["held"].append(int(test.sum()))
        out["tilt"].append(float(np.degrees(np.arccos(min(1.0, abs(frame.axes[2, 2]))))))
        if data.noise is not None:
            out["noise"].append(float(np.sqrt(np.mean(data.noise[test][ok] ** 2))) * data.unit)
        for name, pred in preds.items():
            local = frames[name].to_local(test_w[ok])
            row = out["rows"][name]
            row["rms"].append(float(np.sqrt(np.mean((pred[ok] - local[:, 2]) ** 2))) * data.unit)
            if data.truth is not None:
                true = true_local_heights(frames[name], local[:, :2], data.truth, local[:, 2])
                row["rms_true"].append(float(np.sqrt(np.mean((pred[ok] - true) ** 2))) * data.unit)
        log(f"[heldout] {data.name}: seed {seed} done "
            f"({ok.sum():,} of {test.sum():,} held-out points scored)")
    return out


def table(data: Dataset, result: dict) -> list[str]:
    """The markdown table of one dataset's `evaluate` result, with its notes."""
    rows = result["rows"]
    ref = np.mean(rows["linear TIN"]["rms"])
    rbf = np.mean(rows[RBF]["rms"]) if RBF in rows else np.nan
    truth = data.truth is not None
    head = "| method | RMS m | ratio to TIN | ratio to RBF | seconds |"
    rule = "|---|---:|---:|---:|---:|"
    if truth:
        ref_true = np.mean(rows["linear TIN"]["rms_true"])
        head = ("| method | RMS m (held-out) | ratio to TIN | ratio to RBF | RMS m (true heights) | ratio to TIN "
                "| seconds |")
        rule = "|---|---:|---:|---:|---:|---:|---:|"
    seeds = len(result["held"])
    lines = [f"### {data.name}", "",
             f"{len(data.points):,} points ({data.unit:g} m per unit), {seeds} seed(s); held out "
             f"{np.mean(result['held']):,.0f}, scored {np.mean(result['scored']):,.0f} (covered by every "
             f"method); c1mesh's frame is tilted {np.mean(result['tilt']):.2f}° from z.", "", head, rule]
    for name, row in rows.items():
        rms = np.mean(row["rms"])
        spread = f" ± {np.std(row['rms']):.2g}" if seeds > 1 else ""
        cells = [f"{rms:.4g}{spread}", f"{rms / ref:.3f}", f"{rms / rbf:.3f}"]
        if truth:
            cells += [f"{np.mean(row['rms_true']):.4g}", f"{np.mean(row['rms_true']) / ref_true:.3f}"]
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {np.mean(row['seconds']):.2f} |")
    for name, why in result["skipped"].items():
        lines.append(f"| {name} | skipped: {why} |" + " |" * (len(rule.split("|")) - 4))
    lines.append("")
    if truth:
        lines.append(f"Noise floor (RMS of the added noise at the scored points): "
                     f"{np.mean(result['noise']):.4g} m.")
    for name, row in rows.items():
        notes = [n for n in row["notes"] if n]
        if notes:
            lines.append(f"- {name}: chosen per seed: {', '.join(notes)}")
    lines.append("")
    return lines


def section(quick: bool, seeds: tuple[int, ...], max_points: int | None, command: str,
            peers: str = "all", log=print, sets: list[Dataset] | None = None) -> Section:
    """The RESULTS.md section: the method notes, then one table per dataset."""
    from benchmarks.report import machine

    sec = Section(TITLE)
    versions = [f"gmt {gmt_version()}" if not gmt_status() else "gmt absent"]
    if not verde_status():
        import verde
        versions.append(f"verde {verde.__version__}")
    sec.add(f"Reproduce: `{command}`{' (QUICK: subsampled, 1 seed; not results)' if quick else ''}.",
            "", *machine(), f"- peers: {', '.join(versions)}", "",
            __doc__.split("\n\n", 2)[2].strip(), "")
    why = smooth_status()
    if why:
        sec.add(why, "")
    for data in sets if sets is not None else datasets():
        data = data.subsample(max_points)
        t = time.perf_counter()
        result = evaluate(data, seeds, peers, log)
        sec.add(*table(data, result))
        log("\n".join(table(data, result)))
        log(f"[heldout] {data.name}: {time.perf_counter() - t:.0f} s")
    return sec


def run(cfg: Config) -> Section:
    """The section of `python -m benchmarks`: --quick there is a smoke run (1,500 points, so
    that verde's O(n³) fits take seconds, not the ~20 s per set they take at 3,000)."""
    if cfg.quick:
        return section(True, (0,), 1_500, "python -m benchmarks --quick",
                       log=lambda *a: print(*a, file=sys.stderr))
    return section(False, tuple(range(5)), None, "python -m benchmarks",
                   log=lambda *a: print(*a, file=sys.stderr))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.heldout",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="1 seed, each set subsampled to 20,000 points")
    parser.add_argument("--seeds", type=int, default=None, help="held-out splits (default 5; --quick 1)")
    parser.add_argument("--write", action="store_true",
                        help=f"replace the '{TITLE}' section of benchmarks/RESULTS.md")
    args = parser.parse_args(argv)
    if args.quick and args.write:
        parser.error("--write keeps full runs only: a --quick run's numbers are not results")
    seeds = tuple(range(args.seeds if args.seeds else (1 if args.quick else 5)))
    command = " ".join(["python -m benchmarks.heldout", *(sys.argv[1:] if argv is None else argv)])
    sec = section(args.quick, seeds, 20_000 if args.quick else None, command)
    if args.write:
        write_section(ROOT / "benchmarks" / "RESULTS.md", sec)
        print(f"[heldout] wrote the '{TITLE}' section of benchmarks/RESULTS.md", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
