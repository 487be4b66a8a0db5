"""The one report schema (c1mesh.pipeline.report): every fit path's --report follows it.

Each path is run through the CLI on a small input: the plane fit (hill.ply), a DEM
(-o x.tif), the perspective fit of a synthetic depth frame, `--seamless -o` and `-O` of
two files side by side, and the memory-bounded fit (--memory 1M). Every report must pass
validate_report and carry the same required keys; validate_report must flag a report with
a key taken out.
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from c1mesh.cli import main
from c1mesh.pipeline.report import OPTIONAL, REQUIRED, REQUIRED_PARTS, ReportCore, validate_report
from depth_scenes import tilted_plane, write_organised_pcd
from terrain_scenes import write_terrain_las


def _report(tmp_path, args, name) -> dict:
    path = tmp_path / f"{name}.json"
    result = CliRunner().invoke(main, ["fit", *map(str, args), "--report", str(path)])
    assert result.exit_code == 0, result.output
    return json.loads(path.read_text())


def _plane(tmp_path):
    return _report(tmp_path, ["data_samples/hill.ply", "-o", tmp_path / "hill.ply", "--level", "2"], "plane")


def _dem(tmp_path):
    return _report(tmp_path, ["data_samples/4_6_crop.las", "--classes", "2", "-o", tmp_path / "dem.tif",
                              "--resolution", "2"], "dem")


def _perspective(tmp_path):
    points, normals = tilted_plane(12)
    source = write_organised_pcd(tmp_path / "frame.pcd", points, normals, (12, 12))
    return _report(tmp_path, [source, "-o", tmp_path / "frame.ply", "--frame", "perspective"], "perspective")


def _survey(tmp_path):
    parts = [tmp_path / "west.las", tmp_path / "east.las"]
    write_terrain_las(parts[0], 1200, seed=1)
    write_terrain_las(parts[1], 1200, seed=2, offset=(17.3, 0.0))
    return parts


def _seamless_one(tmp_path):
    return _report(tmp_path, [*_survey(tmp_path), "--seamless", "-o", tmp_path / "survey.ply", "--level", "2"],
                   "seamless_o")


def _seamless_split(tmp_path):
    return _report(tmp_path, [*_survey(tmp_path), "--seamless", "-O", tmp_path / "split", "--level", "2"],
                   "seamless_O")


def _tiled(tmp_path):
    source = tmp_path / "terrain.las"
    write_terrain_las(source, 24000)      # 4 tiles of >= 10000 points (bounded_fit)
    return _report(tmp_path, [source, "--classes", "2", "-o", tmp_path / "tiled.ply", "--level", "2",
                              "--memory", "1M"], "tiled")


PATHS = {"plane": _plane, "dem": _dem, "perspective": _perspective, "seamless -o": _seamless_one,
         "seamless -O": _seamless_split, "tiled": _tiled}


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    return {name: run(tmp_path_factory.mktemp(name.replace(" ", "_"))) for name, run in PATHS.items()}


@pytest.mark.parametrize("path", list(PATHS))
def test_every_path_follows_the_schema(reports, path):
    assert validate_report(reports[path]) == []


def test_every_path_has_the_same_required_keys(reports):
    for name, report in reports.items():
        assert set(REQUIRED) <= set(report), name
        assert set(report) - set(REQUIRED) <= set(OPTIONAL), name
        for section, keys in REQUIRED_PARTS.items():
            assert set(keys) <= set(report[section]), (name, section)


def test_the_paths_say_what_they_are(reports):
    """Keys whose value tells the paths apart: the frame kind, the level's source, the
    nulls the schema documents (no refinement for a DEM; no one interpolator in tiles)."""
    assert reports["perspective"]["frame"]["kind"] == "perspective"
    assert {reports[p]["frame"]["kind"] for p in PATHS if p != "perspective"} == {"axis"}
    assert reports["dem"]["level"] is None and reports["dem"]["output_mesh"] is None
    assert "raster" in reports["dem"]
    assert reports["tiled"]["c1_certificate"] is None and reports["tiled"]["tiles"] > 1
    assert reports["plane"]["level"] == reports["tiled"]["level"] == 2
    names = {p: [Path(name).name for name in reports[p]["input"]] for p in ("seamless -o", "seamless -O")}
    assert names["seamless -o"] == names["seamless -O"] == ["west.las", "east.las"]
    assert len(reports["seamless -O"]["output"]) == 2
    assert reports["perspective"]["threads"] == reports["plane"]["threads"]
    for name in ("plane", "perspective", "seamless -o", "tiled"):      # each triangle became level² faces
        report = reports[name]
        assert report["output_mesh"]["faces"] == report["triangles"]["after_trim"] * report["level"] ** 2, name


def test_the_report_core_is_the_required_table_and_refuses_a_missing_key():
    """ReportCore's fields are REQUIRED's keys in order, with no defaults: a path that
    forgets one cannot build its report."""
    from dataclasses import MISSING, fields

    assert [f.name for f in fields(ReportCore)] == list(REQUIRED)
    assert all(f.default is MISSING for f in fields(ReportCore))
    values = {key: None for key in REQUIRED}
    assert list(ReportCore(**values).as_dict()) == list(REQUIRED)
    del values["pieces"]
    with pytest.raises(TypeError):
        ReportCore(**values)


def test_validate_report_flags_a_missing_or_undeclared_key(reports):
    report = dict(reports["plane"])
    del report["threads"]
    assert validate_report(report) == ["missing required key 'threads'"]
    report = dict(reports["plane"], points={"read": 3})
    assert validate_report(report) == ["missing points.kept"]
    report = dict(reports["plane"], surprise=1)
    assert validate_report(report) == ["undeclared key 'surprise' (add it to REQUIRED or OPTIONAL)"]


def test_cli_readme_documents_every_key():
    """cli/README.md's *The report* tables name exactly the schema's keys."""
    import re

    text = (Path(__file__).parents[1] / "cli" / "README.md").read_text()
    section = text[text.index("### The report (`--report`)"):text.index("## `c1mesh info")]
    documented = re.findall(r"^\| `([a-z_0-9]+)` \|", section, flags=re.M)
    assert documented == list(REQUIRED) + list(OPTIONAL)
