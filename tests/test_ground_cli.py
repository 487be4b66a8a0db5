"""LiDAR ground by default (issue 39): `c1mesh fit` of LAS/LAZ takes class 2, or the ground
filter's ground for an unclassified tile; `c1mesh ground` writes the filter's classes."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from c1mesh.cli import main, usage_error
from c1mesh.testing.ground_scenes import filter_scores
from stderr_lines import stderr_on_a_terminal
from terrain_scenes import write_terrain_las

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"
CLASSIFIED = SAMPLES / "4_6_crop.las"
UNCLASSIFIED = SAMPLES / "4_6_crop_unclassified.laz"
US_FOOT = 1200 / 3937


def _invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _one_error_line(result) -> str:
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("c1mesh: error: "), result.output
    return lines[0]


def test_the_unclassified_sample_is_the_classified_one_stripped():
    import laspy

    classified, stripped = laspy.read(CLASSIFIED), laspy.read(UNCLASSIFIED)
    assert np.array_equal(classified.x, stripped.x) and np.array_equal(classified.z, stripped.z)
    assert not np.asarray(stripped.classification).any()


def test_ground_command_writes_the_filters_classes(tmp_path):
    """Every record and dimension kept, classes 2 and 1 only, and the ground scores within
    issue 39's 3% bar against the provider's class 2 (the stripped sample's origin)."""
    import laspy

    out = tmp_path / "classified.las"
    result = _invoke("ground", UNCLASSIFIED, "-o", out, "--report", tmp_path / "r.json")
    assert result.exit_code == 0, result.output
    written, source, truth = laspy.read(out), laspy.read(UNCLASSIFIED), laspy.read(CLASSIFIED)
    assert list(written.point_format.dimension_names) == list(source.point_format.dimension_names)
    for name in ("X", "Y", "Z", "intensity", "gps_time", "return_number"):
        assert np.array_equal(written[name], source[name])
    assert set(np.unique(written.classification)) == {1, 2}
    scores = filter_scores(np.asarray(truth.classification) == 2, np.asarray(written.classification) == 2)
    assert scores.total <= 3.0
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["ground"] == int((np.asarray(written.classification) == 2).sum())
    assert report["filter"]["metres_per_unit"][0] == pytest.approx(US_FOOT)


def test_ground_command_refuses_bad_paths_before_reading(tmp_path):
    assert usage_error(["ground", "scan.ply", "-o", "out.las"]).startswith("c1mesh: error: ground classifies LAS/LAZ")
    assert "must be a .las or .laz" in usage_error(["ground", "tile.laz", "-o", "out.ply"])
    result = _invoke("ground", CLASSIFIED, "-o", CLASSIFIED)
    assert result.exit_code == 1 and "refusing to overwrite an input" in _one_error_line(result)
    broken = tmp_path / "broken.las"
    broken.write_bytes(b"LASF" + bytes(50))
    result = _invoke("ground", broken, "-o", tmp_path / "out.las")
    assert result.exit_code == 1 and "broken.las" in _one_error_line(result)
    assert not (tmp_path / "out.las").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.las"]          # no temporary left


def _fit_report(tmp_path, source, *options) -> dict:
    report = tmp_path / "report.json"
    result = _invoke("fit", "--smooth", "off", source, "-o", tmp_path / "out.ply", "--level", "1", "--report", report, *options)
    assert result.exit_code == 0, result.output
    return json.loads(report.read_text())


def test_fit_takes_the_ground_class_by_default(tmp_path):
    """A classified tile: the class-2 points (counted by laspy) are the fit's, as with --classes 2."""
    import laspy

    ground = int((np.asarray(laspy.read(CLASSIFIED).classification) == 2).sum())
    report = _fit_report(tmp_path, CLASSIFIED)
    assert report["classes"] == {"selected": [2], "source": "file", "points_read": 23875, "points_kept": ground}
    assert report["points"]["read"] == ground
    explicit = _fit_report(tmp_path, CLASSIFIED, "--classes", "2")
    assert explicit["classes"]["source"] == "option" and explicit["points"] == report["points"]


def test_fit_of_an_unclassified_tile_runs_the_filter(tmp_path):
    report = _fit_report(tmp_path, UNCLASSIFIED)
    chosen = report["classes"]
    assert chosen["source"] == "filter" and chosen["reason"] == "the file has no ground class 2"
    assert chosen["filter"]["parameters"]["cell"] == 1.0 and chosen["filter"]["units"] == "US survey foot"
    assert report["points"]["read"] == chosen["points_kept"] == chosen["filter"]["ground"]


def test_dtm_of_the_unclassified_tile_matches_the_class_2_dtm(tmp_path):
    """Issue 39's DTM check on the bundled tile: the DEM of the stripped tile (no option)
    within 0.2 m (95th percentile) of the DEM of the provider's class 2."""
    import rasterio

    dems = []
    for source, name in ((UNCLASSIFIED, "u.tif"), (CLASSIFIED, "c.tif")):
        result = _invoke("fit", "--smooth", "off", source, "-o", tmp_path / name, "--resolution", "3")
        assert result.exit_code == 0, result.output
        with rasterio.open(tmp_path / name) as raster:
            dems.append(raster.read(1, masked=True))
    assert dems[0].shape == dems[1].shape
    gap = np.abs(dems[0] - dems[1]).compressed() * US_FOOT
    assert gap.size > 0.9 * dems[1].count() and np.percentile(gap, 95) <= 0.2


def test_classes_all_fits_every_point_as_before(tmp_path):
    """--classes all keeps the roofs and trees of 4_6_crop: refused as no height field."""
    result = _invoke("fit", "--smooth", "off", CLASSIFIED, "-o", tmp_path / "top.ply", "--classes", "all")
    assert result.exit_code == 1 and "not a height field" in _one_error_line(result)


def test_class_choice_usage_errors():
    assert "--classes needs LAS/LAZ input" in usage_error(["fit", "--smooth", "off", "hill.ply", "-o", "o.ply", "--classes", "filter"])
    assert "expected auto, all, filter" in usage_error(["fit", "--smooth", "off", "t.laz", "-o", "o.ply", "--classes", "ground"])
    assert usage_error(["fit", "--smooth", "off", "hill.ply", "-o", "o.ply"]) is None          # auto: nothing for a PLY


def test_tiled_fit_takes_class_2_by_default(tmp_path):
    """The memory-bounded fit selects class 2 by default, as in memory."""
    classified = tmp_path / "two.las"
    write_terrain_las(classified, 24000, classes=(2, 5))
    report = _fit_report(tmp_path, classified, "--memory", "1M")
    assert report["classes"] == {"selected": [2], "source": "file"} and report["tiles"] > 1


@pytest.mark.parametrize("source,extra", [(UNCLASSIFIED, ()), (CLASSIFIED, ("--classes", "filter"))])
def test_the_tiled_fit_filters_ground_tile_by_tile_as_the_whole_fit_does(tmp_path, source, extra):
    """Beyond --memory the filter runs on tiles with its halo (survey.ground_pass): 9 filter
    tiles and 4 fit tiles give the points, the report's classes and the mesh of the
    in-memory fit, vertex for vertex (every vertex an input point at level 1)."""
    import trimesh

    from c1mesh.core.plan import TiledRun
    from c1mesh.pipeline.driver import FitOptions
    from c1mesh.pipeline.run import fit

    options = FitOptions(smooth="off", level=1, classes="filter" if extra else "auto")
    whole = fit(str(source), str(tmp_path / "whole.ply"), options).report
    tiled = fit(str(source), tmp_path / "tiled.ply", FitOptions(smooth="off", level=1, memory=10**9, classes=options.classes),
                tiles=TiledRun(per_tile=3000)).report
    assert tiled["tiles"] == 4 and tiled["seconds"]["ground"] > 0          # 9 filter tiles: ceil(sqrt(23875/3000))²
    assert tiled["classes"] == whole["classes"] and whole["classes"]["source"] == "filter"
    assert tiled["triangles"]["removed"] == whole["triangles"]["removed"]     # the ground's trim rules, not all points'
    meshes = [trimesh.load(tmp_path / name, process=False, force="mesh") for name in ("whole.ply", "tiled.ply")]
    keys = [set(map(tuple, np.asarray(m.vertices))) for m in meshes]
    assert keys[0] == keys[1] and len(keys[0]) == whole["classes"]["points_kept"]
    faces = [{tuple(sorted(map(tuple, np.asarray(m.vertices)[f]))) for f in np.asarray(m.faces)} for m in meshes]
    assert faces[0] == faces[1]


def test_note_on_a_terminal_only(tmp_path):
    args = ["fit", "--smooth", "off", str(CLASSIFIED), "-o", str(tmp_path / "g.ply"), "--level", "1"]
    shown = stderr_on_a_terminal(args)
    assert "c1mesh: note: " in shown and "fitting the ground class 2 (9003 of 23875 points)" in shown
    assert "note:" not in _invoke(*args).output
