"""The smoothing default (pipeline.plan.resolved_smoothing, issue 38): the lattice fit where
the gradients are estimated over a height field, the pixel grid's smoothing fit where they
are estimated in the perspective frame, the exact fit where the file has normals; anything
given is kept."""
from __future__ import annotations

import numpy as np
import pytest

from c1mesh.pipeline.driver import FitOptions, build_surface, load_cloud
from c1mesh.pipeline.plan import resolved_smoothing
from test_smoothing_fit import SAMPLES


@pytest.mark.parametrize("estimated, perspective, spacing, expected", [
    (True, False, None, ("auto", "auto")),
    (True, False, 2.0, ("auto", 2.0)),
    (False, False, None, ("off", None)),
    (False, False, 2.0, ("auto", 2.0)),          # a lattice asked for: a smoothing fit's
    (True, True, None, ("auto", None)),          # the chart keeps every point: no lattice
    (False, True, None, ("off", None)),
])
def test_the_default_resolves_by_where_the_gradients_come_from(estimated, perspective, spacing, expected):
    options = resolved_smoothing(FitOptions(spacing=spacing), estimated, perspective)
    assert (options.smooth, options.spacing) == expected


@pytest.mark.parametrize("smooth", ["off", "auto", 3.0])
def test_a_given_smooth_is_kept(smooth):
    options = FitOptions(smooth=smooth)
    assert resolved_smoothing(options, True) is options


def test_the_fits_follow_the_files_normals():
    """A LAS tile (no normals) is fitted on the lattice, a PLY with normals exactly."""
    las = build_surface(load_cloud(SAMPLES / "4_6_crop.las", FitOptions(classes=(2,))), FitOptions(classes=(2,)))
    assert las.smoothing is not None and las.on_lattice
    ply = build_surface(load_cloud(SAMPLES / "hill.ply", FitOptions()), FitOptions())
    assert ply.smoothing is None and not ply.on_lattice


def test_a_depth_frame_is_smoothed_unless_its_file_has_normals(tmp_path):
    """The perspective frame follows the same rule: an organised frame without normals (the
    grid's estimated) reports a smoothing strength, the same frame with its exact normals
    is interpolated exactly."""
    from c1mesh.pipeline.run import fit
    from depth_scenes import cylinder_from_inside, write_organised_pcd

    points, normals = cylinder_from_inside(24)
    bare = write_organised_pcd(tmp_path / "bare.pcd", points, np.full_like(points, np.nan), (24, 24))
    with_normals = write_organised_pcd(tmp_path / "normals.pcd", points, normals, (24, 24))
    estimated = fit(bare, None, FitOptions(level=1))
    given = fit(with_normals, None, FitOptions(level=1))
    assert estimated.report["frame"]["kind"] == given.report["frame"]["kind"] == "perspective"
    assert (estimated.report["normals"], given.report["normals"]) == ("grid", "file")
    assert estimated.report["smoothing"]["strength"] > 0 and "smoothing" not in given.report
