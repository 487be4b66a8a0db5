"""Smoke test of benchmarks/heldout.py (issue 24's held-out accuracy benchmark) at tiny size.

The harness is checked end to end against independent truths: the analytic terrain's
gradients against central differences, the Newton heights along a tilted frame's axis against
points placed on the surface, and on noise-free analytic data at fine sampling the order of
the methods, a mathematical fact: the linear TIN's error is O(h²) while Clough–Tocher's and
c1mesh's (C1, cubic and higher order) are O(h³) or better, so at ~0.4 m spacing on a surface
varying over metres the TIN's held-out RMS is the largest.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks import heldout  # noqa: E402


def test_synthetic_gradients_match_central_differences():
    xy = np.random.default_rng(0).random((200, 2)) * 100
    _, grad = heldout.synthetic_height(xy)
    h = 1e-5
    for axis in (0, 1):
        step = np.zeros(2)
        step[axis] = h
        fd = (heldout.synthetic_height(xy + step)[0] - heldout.synthetic_height(xy - step)[0]) / (2 * h)
        np.testing.assert_allclose(grad[:, axis], fd, rtol=1e-6, atol=1e-7)


def test_true_heights_along_a_tilted_axis_land_on_the_surface():
    """Points on the surface z = f(x, y), seen in a frame tilted by ~5°: Newton from a wrong
    start (0) must return each point's own local height."""
    from c1mesh.stages.frame import ScanFrame

    a = np.radians(5.0)
    axes = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
    frame = ScanFrame(origin=np.array([50.0, 50.0, 1.0]), axes=axes)
    xy = np.random.default_rng(1).random((300, 2)) * 100
    world = np.column_stack([xy, heldout.synthetic_height(xy)[0]])
    local = frame.to_local(world)
    t = heldout.true_local_heights(frame, local[:, :2], heldout.synthetic_height, np.zeros(len(xy)))
    np.testing.assert_allclose(t, local[:, 2], atol=1e-9)


def test_held_out_split_is_ten_percent_and_seeded():
    a, b = heldout.held_out(1000, 3), heldout.held_out(1000, 3)
    assert a.sum() == 100 and np.array_equal(a, b) and not np.array_equal(a, heldout.held_out(1000, 4))


def test_crs_unit_reads_the_coordinate_unit():
    wkt = 'PROJCRS[..LENGTHUNIT["metre",1]..LENGTHUNIT["US survey foot",0.304800609601219]]'
    assert heldout.crs_unit(wkt) == pytest.approx(1200 / 3937)
    assert heldout.crs_unit(None) == 1.0


@pytest.mark.slow
def test_noise_free_terrain_tin_is_worst_end_to_end():
    """3,000 noise-free points over 20 m (spacing ~0.37 m), one seed, the scipy peers and
    c1mesh through the whole harness (evaluate, table)."""
    data = heldout.synthetic(3_000, 0.0, seed=5, size=20.0, name="tiny noise-free")
    result = heldout.evaluate(data, seeds=(0,), peers="scipy", log=lambda *a: None)
    rows = result["rows"]
    assert {"linear TIN", "Clough–Tocher", "RBF TPS (neighbors=50)", "c1mesh exact",
            "c1mesh overshoot=off"} <= set(rows)
    assert not any(name.startswith("GMT") or name.startswith("verde") for name in rows)
    assert result["held"] == [300] and result["scored"][0] > 0.9 * 300
    tin = rows["linear TIN"]["rms"][0]
    assert tin > rows["Clough–Tocher"]["rms"][0]
    assert tin > rows["c1mesh exact"]["rms"][0]
    for row in rows.values():       # noise-free: the held-out heights are the true heights
        assert row["rms_true"][0] == pytest.approx(row["rms"][0], rel=1e-6, abs=1e-12)
    assert result["noise"] == [0.0]
    text = "\n".join(heldout.table(data, result))
    assert "| linear TIN | " in text and "| 1.000 |" in text and "Noise floor" in text


def test_write_section_replaces_only_its_own_section(tmp_path):
    from benchmarks.common import Section

    path = tmp_path / "RESULTS.md"
    path.write_text(f"# r\n\n## A\n\na\n\n## {heldout.TITLE}\n\nold\n\n## B\n\nb\n")
    sec = Section(heldout.TITLE)
    sec.add("new")
    heldout.write_section(path, sec)
    assert path.read_text() == f"# r\n\n## A\n\na\n\n## {heldout.TITLE}\n\nnew\n\n## B\n\nb\n"
    other = tmp_path / "other.md"
    other.write_text("# r\n\n## A\n\na\n")
    heldout.write_section(other, sec)
    assert other.read_text() == f"# r\n\n## A\n\na\n\n## {heldout.TITLE}\n\nnew\n"



def test_write_section_can_keep_the_runs_it_replaces(tmp_path):
    """keep_earlier (the DTM job's --write): the old head becomes the first earlier run,
    above those the section kept; the sections around it do not change."""
    from benchmarks.common import Section, write_section

    path = tmp_path / "RESULTS.md"
    path.write_text("# r\n\n## T\n\nrun 2\n\n### Earlier runs\n\nrun 1\n\n## B\n\nb\n")
    sec = Section("T")
    sec.add("run 3")
    write_section(path, sec, keep_earlier=True)
    assert path.read_text() == ("# r\n\n## T\n\nrun 3\n\n### Earlier runs\n\nThe run before:\n\nrun 2\n\n"
                                "run 1\n\n## B\n\nb\n")

def test_gmt_runs_at_the_nearest_neighbour_spacing_not_the_hull_area_one():
    """Issue 38: GMT gets the nearest-neighbour spacing. On a jittered 0.5 m grid every
    point's nearest neighbour is within the jitter of 0.5 m, while sqrt(hull area / n) is
    0.5 m too; on clustered points (pairs 0.1 m apart on a 1 m grid) the two differ: the
    nearest-neighbour spacing is the pair distance, the hull-area one about 0.7 m."""
    x, y = np.meshgrid(np.arange(40) * 0.5, np.arange(40) * 0.5)
    grid = np.column_stack([x.ravel(), y.ravel()])
    assert heldout.nearest_spacing(grid) == pytest.approx(0.5)
    x, y = np.meshgrid(np.arange(30.0), np.arange(30.0))
    base = np.column_stack([x.ravel(), y.ravel()])
    pairs = np.concatenate([base, base + [0.1, 0.0]])
    assert heldout.nearest_spacing(pairs) == pytest.approx(0.1)
    assert heldout.mean_spacing(pairs) == pytest.approx(np.sqrt((29.1 * 29) / len(pairs)))


def test_table_gives_every_rms_as_a_ratio_to_the_rbf():
    data = heldout.Dataset("toy", np.zeros((10, 3)), unit=1.0)
    rows = {name: {"rms": [value], "rms_true": [], "seconds": [1.0], "notes": [""]}
            for name, value in (("linear TIN", 0.4), (heldout.RBF, 0.2), ("c1mesh smooth=auto", 0.21))}
    lines = heldout.table(data, {"rows": rows, "skipped": {}, "scored": [9], "held": [1], "noise": [], "tilt": [0.0]})
    row = next(line for line in lines if line.startswith("| c1mesh smooth=auto"))
    assert row.split("|")[2:5] == [" 0.21 ", " 0.525 ", " 1.050 "]
