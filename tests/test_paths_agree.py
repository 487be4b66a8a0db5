"""Every path of `c1mesh fit` gives the same answer to the same bad or odd input: in memory,
in tiles under --memory, as one part per input with --seamless -O (in memory and in
tiles), and with the tiles on a Dask cluster. The same exit code, the same first line on
stderr, no output left behind when it fails, and for the input that fits the same advice
in the report to smooth its noisy heights.

Ground truth is the in-memory fit's check (stages.height_field, stages.height_gradients,
the LAS reader); the other paths must reach the same verdict with the same numbers, not a
later stage's error (a trim with nothing left, a solver's shape error).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

laspy = pytest.importorskip("laspy")
distributed = pytest.importorskip("distributed")

from c1mesh.cli import main
from stderr_lines import ADVICE

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"
BUDGET = "8M"
"""A --memory budget that the 24k-30k-point inputs below exceed, so they are fitted in tiles."""


def _las(path: Path, x, y, z, classes) -> Path:
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [0.001] * 3, [0, 0, 0]
    record = laspy.ScaleAwarePointRecord.zeros(len(x), header=header)
    record.x, record.y, record.z = x, y, z
    record.classification = np.broadcast_to(np.asarray(classes, np.uint8), (len(x),))
    with laspy.open(str(path), mode="w", header=header) as writer:
        writer.write_points(record)
    return path


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, list[str]]:
    """Name -> the input and its options: the 4_6_crop vegetation the issue names, a class
    the file lacks, an empty file, two layers, points at two plane positions, a class with
    two points, a trim that leaves nothing to smooth, a ground sample that fits, and an
    unclassified tile whose ground the filter finds (tile by tile beyond --memory)."""
    folder = tmp_path_factory.mktemp("inputs")
    rng = np.random.default_rng(0)
    n = 30000
    x, y = rng.uniform(0, 100, n), rng.uniform(0, 100, n)
    two = rng.integers(0, 2, n)
    few = np.ones(n, np.uint8)
    few[:2] = 2
    return {
        "vegetation": [str(SAMPLES / "4_6_crop.las"), "--classes", "1"],
        "missing class": [str(SAMPLES / "autzen_trim.laz"), "--classes", "7"],
        "empty": [str(_las(folder / "empty.las", [], [], [], 2))],
        "two layers": [str(_las(folder / "layers.las", x, y, np.where(two == 1, 20.0, 0.0) + 0.01 * x, 2))],
        "two positions": [str(_las(folder / "two.las", 1.0 * two, 2.0 * two, rng.uniform(0, 1, n), 2))],
        "two ground points": [str(_las(folder / "few.las", x, y, np.sin(x / 9), few)), "--classes", "2"],
        "trimmed away, smoothing": [str(SAMPLES / "autzen_trim.laz"), "--classes", "2", "--max-edge", "0.001",
                                    "--smooth", "auto"],
        "ground": [str(SAMPLES / "autzen_trim.laz"), "--classes", "2", "--level", "1", "--smooth", "off"],
        "unclassified": [str(SAMPLES / "4_6_crop_unclassified.laz"), "--level", "1"],     # the ground filter
    }


PATHS = {
    "in memory": lambda out, cluster: ["-o", str(out / "fit.ply")],
    "--memory": lambda out, cluster: ["-o", str(out / "fit.ply"), "--memory", BUDGET],
    "--seamless -O": lambda out, cluster: ["--seamless", "-O", str(out)],
    "--seamless -O --memory": lambda out, cluster: ["--seamless", "-O", str(out), "--memory", BUDGET],
    "dask": lambda out, cluster: ["-o", str(out / "fit.ply"), "--memory", BUDGET,
                                  "--scheduler", cluster.scheduler_address],
}


@pytest.fixture(scope="module")
def cluster():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as local:
        yield local


def _first_line(text: str) -> str:
    lines = text.splitlines()
    return lines[0] if lines else ""


@pytest.mark.parametrize("case", ["vegetation", "missing class", "empty", "two layers", "two positions",
                                  "two ground points", "trimmed away, smoothing", "ground", "unclassified"])
def test_every_path_gives_the_same_answer(tmp_path, inputs, cluster, case):
    answers = {}
    for name, path_args in PATHS.items():
        out = tmp_path / name.replace(" ", "_").strip("-")
        out.mkdir()
        report = tmp_path / f"{out.name}.json"
        result = CliRunner().invoke(main, ["fit", *inputs[case], *path_args(out, cluster), "--report", str(report)])
        facts = {} if result.exit_code else json.loads(report.read_text())
        chosen = facts.get("classes") or {}
        answers[name] = (result.exit_code, _first_line(result.stderr), facts.get("suggestion"),
                         str(chosen.get("selected")), chosen.get("source"))
        if result.exit_code:
            assert sorted(p.name for p in out.iterdir()) == [], f"{name} left output behind"
        else:
            assert any(out.iterdir()), f"{name} wrote nothing"
    assert len(set(answers.values())) == 1, json.dumps(answers, indent=1)
    expected_exit = 0 if case in ("ground", "unclassified") else 1
    assert answers["in memory"][0] == expected_exit
    if case == "ground":                  # noisy LiDAR ground: every path's report advises --smooth auto
        assert ADVICE.fullmatch(f"c1mesh: note: {inputs[case][0]}: {answers['in memory'][2]}")
    if case == "unclassified":            # no class 2: every path fits the ground filter's ground
        assert answers["in memory"][3:] == ("[2]", "filter")


def test_the_budget_really_tiles_the_inputs(tmp_path):
    """The --memory paths above must run the tiled fit in several tiles, not the in-memory
    fit (a tile holds at least 10,000 points: the inputs above have 14k-30k)."""
    report = tmp_path / "r.json"
    result = CliRunner().invoke(main, ["fit", str(SAMPLES / "autzen_trim.laz"), "--classes", "2", "--level", "1",
                                       "-o", str(tmp_path / "fit.ply"), "--memory", BUDGET, "--report", str(report)])
    assert result.exit_code == 0, result.output
    assert json.loads(report.read_text())["tiles"] > 1


def test_the_tiled_stacking_test_measures_what_memory_measures(tmp_path):
    """Beyond 40,000 positions the spacing h is measured on a sample (every few survey
    numbers): the tiled fit's h and stacked count equal the in-memory fit's to the bit, on
    90k points with 1.5% raised by 10 m and a few thousand exact duplicates (near the
    origin both frames' local coordinates agree to the bit; 4,000 km from it they may
    differ in a last bit, as test_tiled_smoothing allows)."""
    rng = np.random.default_rng(1)
    n = 90000
    x, y = np.round(rng.uniform(0, 300, n), 2), np.round(rng.uniform(0, 300, n), 2)
    z = 5 * np.sin(x / 30) + 0.02 * rng.normal(size=n)
    z[rng.random(n) < 0.015] += 10
    x[:3000], y[:3000] = x[3000:6000], y[3000:6000]
    source = _las(tmp_path / "near.las", x, y, z, 2)
    points = {}
    for name, extra in (("memory", []), ("tiles", ["--memory", "30M"])):
        report = tmp_path / f"{name}.json"
        result = CliRunner().invoke(main, ["fit", str(source), "--level", "1", "--smooth", "off", "-q", "-o",
                                           str(tmp_path / f"{name}.ply"), "--report", str(report), *extra])
        assert result.exit_code == 0, result.output
        points[name] = json.loads(report.read_text())
    assert points["tiles"]["tiles"] > 1
    memory, tiles = points["memory"]["points"], points["tiles"]["points"]
    assert memory["stacked"] > 1000                        # the raised points and the duplicates
    assert (tiles["stacked"], tiles["spacing"]) == (memory["stacked"], memory["spacing"])
