"""The tiled fit (c1mesh.pipeline.bounded_fit) against the in-memory fit of the same points.

Ground truth: the in-memory stages on the whole cloud (estimate_normals, choose_frame,
height_field, delaunay, the long-edge trim, limiter.control_overshoot or unit-normal
directions, RSDInterpolator, refinement), which never cut the survey. The tiled fit must
give the same mesh: the same vertices to rounding, the same faces (compared through the
matched vertices). The tiled limiter alone, given the in-memory height field, must give
the in-memory limiter's gradients to the bit.
"""
from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

laspy = pytest.importorskip("laspy")

from click.testing import CliRunner

from c1mesh.cli import main
from stderr_lines import stderr_on_a_terminal
from c1mesh.stages.curtains import REASONS, remove_curtains
from c1mesh.stages.frame import choose_frame
from c1mesh.stages.height_field import height_field
from c1mesh.stages.height_gradients import height_neighbours, height_normals
from c1mesh.survey.buffered_delaunay import TileGrid
from c1mesh.engine.interpolator import RSDInterpolator
from c1mesh.stages.limiter import control_overshoot, tile_limits
from c1mesh.stages.normals import estimate_normals
from c1mesh.stages.surface import surface_stream
from c1mesh.pipeline.driver import FitOptions
from c1mesh.survey.tile_spill import TileSpill
from c1mesh.core.plan import TiledRun
from c1mesh.pipeline.run import fit
from c1mesh.survey.height_runs import HEIGHT
from c1mesh.survey.halos import halo_reach, noise_floors, read_halo
from c1mesh.survey.sizing import fits_in_memory, points_per_tile
from c1mesh.stages.trim import drop_triangles, kept_triangles, peeled, triangles_among, trim
from c1mesh.engine.topology import edge_table
from c1mesh.engine.triangulation import delaunay
from terrain_scenes import write_terrain_las

SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"


def _in_memory(path, classes, level, overshoot="limit", max_edge="auto", gradients="heights"):
    """The whole-cloud fit with the in-memory default trim (long edges, slivers, bow-ties,
    then curtains and what their holes expose: pipeline.build_surface's order); gradients
    fitted to the heights (the default for LAS) or from PCA normals."""
    las = laspy.read(str(path))
    keep = np.isin(np.asarray(las.classification), classes)
    points = np.column_stack([las.x, las.y, las.z])[keep]
    if gradients == "heights":
        normals = height_normals(points, choose_frame(points, None, "z"), k=height_neighbours(16))
    else:
        normals = estimate_normals(points, k=16, towards=(0, 0, 1))
    frame = choose_frame(points, normals, "z")
    hf = height_field(points, normals, frame)
    triangles, report = trim(hf.xy, delaunay(hf.xy), max_edge=max_edge)
    triangles, report = remove_curtains(hf.xy, hf.z, hf.gradients, triangles, report)
    used = np.unique(triangles)
    triangles = np.searchsorted(used, triangles)
    values, gradients, directions, limiter = control_overshoot(hf.xy[used], hf.z[used], hf.gradients[used],
                                                               triangles, overshoot)
    interp = RSDInterpolator(hf.xy[used], values, gradients, triangles=triangles, directions=directions)
    mesh = surface_stream(interp.refinement(level), frame, None).materialize()
    mesh.limiter, mesh.slivers = limiter.as_dict(), report.removed["sliver"]
    mesh.removed = dict(report.removed)
    return mesh, report.max_edge, len(used)


def _match(a, b):
    """(order) with b[order] == a to rounding: vertices matched by lexicographic sorting."""
    ia, ib = np.lexsort(np.round(a, 6).T[::-1]), np.lexsort(np.round(b, 6).T[::-1])
    order = np.empty(len(a), dtype=np.int64)
    order[ia] = ib
    return order


def _assert_exact_merge(paths, whole_path):
    """Merging the meshes at paths by exactly equal vertices gives the mesh at whole_path:
    the same vertex set, bit for bit, and the same faces, each once."""
    whole = trimesh.load(whole_path, process=False, force="mesh")
    keys = np.ascontiguousarray(np.asarray(whole.vertices, float)).view("V24").ravel()
    order = np.argsort(keys)
    faces = []
    for path in paths:
        part = trimesh.load(path, process=False, force="mesh")
        mine = np.ascontiguousarray(np.asarray(part.vertices, float)).view("V24").ravel()
        at = order[np.searchsorted(keys[order], mine)]
        assert np.array_equal(keys[at], mine)                  # every vertex is a whole vertex, bit for bit
        faces.append(np.sort(at[np.asarray(part.faces)], axis=1))
    merged = np.concatenate(faces)
    expected = np.sort(np.asarray(whole.faces), axis=1)
    assert len(np.unique(merged, axis=0)) == len(merged) == len(expected)
    np.testing.assert_array_equal(np.unique(merged, axis=0), np.unique(expected, axis=0))


def _assert_same_mesh(path, whole):
    """The mesh file at path has whole's vertices (to rounding) and faces, each face once."""
    tiled = trimesh.load(path, process=False, force="mesh")
    vertices, faces = np.asarray(tiled.vertices, float), np.asarray(tiled.faces, np.int64)
    assert vertices.shape == whole.vertices.shape
    assert faces.shape == whole.faces.shape
    order = _match(whole.vertices, vertices)
    scale = np.abs(whole.vertices).max()
    np.testing.assert_allclose(vertices[order], whole.vertices, rtol=0, atol=1e-13 * scale)
    inverse = np.empty_like(order)
    inverse[order] = np.arange(len(order))
    faces_tiled = np.sort(inverse[faces], axis=1)
    faces_whole = np.sort(whole.faces, axis=1)
    assert set(map(tuple, faces_tiled.tolist())) == set(map(tuple, faces_whole.tolist()))
    assert len(np.unique(faces_tiled, axis=0)) == len(faces_tiled)     # every face once


@pytest.mark.parametrize("level,overshoot,gradients", [(1, "limit", "auto"), (3, "limit", "auto"),
                                                       (2, "off", "normals"), (2, "limit", "normals")])
def test_tiled_fit_equals_whole_cloud_fit(tmp_path, level, overshoot, gradients):
    source = tmp_path / "terrain.las"
    write_terrain_las(source, 12000, classes=(2, 5))
    whole, max_edge, kept = _in_memory(source, [2], level, overshoot,
                                       gradients="normals" if gradients == "normals" else "heights")
    options = FitOptions(smooth="off", classes=(2,), overshoot=overshoot, level=level, gradients=gradients)
    report = fit(source, tmp_path / "tiled.ply", replace(options, memory=10**9), tiles=TiledRun(per_tile=700)).report
    assert report["tiles"] >= 9
    assert report["max_edge"] == max_edge
    _assert_same_mesh(tmp_path / "tiled.ply", whole)
    assert report["points"]["kept"] == kept
    assert whole.removed["bowtie"] > 0 and whole.removed["thinner_than_noise"] > 0   # both cuts act
    assert report["triangles"]["removed"] == whole.removed
    if overshoot == "limit":
        assert whole.limiter["gradients_limited"] > 100        # the noise makes the limiter act
        assert {k: report["overshoot"][k] for k in whole.limiter} == whole.limiter
    assert sorted(p.name for p in tmp_path.iterdir()) == ["terrain.las", "tiled.ply"]   # no spill left


@pytest.mark.parametrize("rule", ["auto", None])
def test_tiled_fit_of_lidar_ground_equals_whole_fit(tmp_path, rule):
    """Without a trim (None) the survey's hull slivers are peeled (96) and the halo is
    sized by the longest final edge, found by a pass of its own."""
    source = SAMPLES / "4_6_crop.las"
    whole, max_edge, kept = _in_memory(source, [2], 2, max_edge=rule)
    options = FitOptions(smooth="off", classes=(2,), level=2, max_edge=rule)
    report = fit(source, tmp_path / "tiled.ply", replace(options, memory=10**9), tiles=TiledRun(per_tile=1000)).report
    assert report["tiles"] == 16
    assert report["max_edge"] == max_edge
    assert report["triangles"]["removed"]["sliver"] == whole.slivers > 0
    assert report["triangles"]["removed"] == whole.removed
    assert {k: report["overshoot"][k] for k in whole.limiter} == whole.limiter
    _assert_same_mesh(tmp_path / "tiled.ply", whole)


@pytest.mark.parametrize("per_tile", [7000, 1700])
def test_tiled_fit_of_autzen_ground_removes_the_bowties_and_curtains_of_the_whole_fit(tmp_path, per_tile):
    """Autzen ground (26k points) in 4 and 16 tiles: the whole fit's trim cuts bow-tie
    fans (57 triangles, some between fans of equal size) and curtains; the tiled trim
    cuts the same triangles, so the meshes are equal, refined points included (level 2):
    those depend on every vertex gradient, and point 3143's 24th and 25th nearest plane
    neighbours are equally far on the 1 cm grid, so a neighbour rule that broke the tie by
    point numbering gave it another gradient in tiles (by 0.01) and moved refined points
    of its triangles by up to 1.1 cm."""
    source = SAMPLES / "autzen_trim.laz"
    whole, max_edge, kept = _in_memory(source, [2], 2)
    assert whole.removed["bowtie"] > 0
    assert sum(whole.removed[r] for r in REASONS) > 0
    options = FitOptions(smooth="off", classes=(2,), level=2)
    report = fit(source, tmp_path / "tiled.ply", replace(options, memory=10**9), tiles=TiledRun(per_tile=per_tile)).report
    assert report["tiles"] == (4 if per_tile == 7000 else 16)
    assert report["triangles"]["removed"] == whole.removed
    assert {k: report["overshoot"][k] for k in whole.limiter} == whole.limiter
    _assert_same_mesh(tmp_path / "tiled.ply", whole)


class _Temps:
    def __init__(self, directory):
        self.directory = directory

    def new(self, name):
        return self.directory / name


class _Halos:
    """Every tile's halo, read from the spills when asked (HaloCache's tiles and halo)."""

    def __init__(self, spill, files, grid, reach):
        self.spill, self.files, self.grid, self.reach = spill, files, grid, reach

    def tiles(self):
        return list(range(len(self.grid)))

    def halo(self, tile):
        return read_halo(self.spill, self.files, self.grid, tile, self.reach)


def _tiled_limiter(xy, z, gradients, triangles, side, directory):
    """The tiled limiter on a height field held in memory, cut into side x side tiles:
    (noise floors, per tile its TileLimits and its own triangles)."""
    box = (*xy.min(axis=0), *xy.max(axis=0))
    grid = TileGrid(box, side, side)
    spill = TileSpill(grid, directory, "h", record=HEIGHT).__enter__()
    home = grid.tile_of(xy)
    for t in range(len(grid)):
        rows = np.flatnonzero(home == t)
        records = np.empty(len(rows), HEIGHT)
        records["index"], records["x"], records["y"], records["z"] = rows, xy[rows, 0], xy[rows, 1], z[rows]
        records["gx"], records["gy"] = gradients[rows, 0], gradients[rows, 1]
        spill.append(t, records)
    owner = home[triangles.min(axis=1)]
    files = []
    for t in range(len(grid)):
        files.append(directory / f"tri-{t}.npy")
        np.save(files[-1], triangles[owner == t])
    longest = max(np.hypot(*(xy[triangles[:, i]] - xy[triangles[:, (i + 1) % 3]]).T).max() for i in range(3))
    reach = halo_reach(longest)
    floors = noise_floors(_Halos(spill, files, grid, reach), _Temps(directory))
    tiles = [(tile_limits(read_halo(spill, files, grid, t, reach), triangles[owner == t], floors),
              triangles[owner == t]) for t in range(len(grid)) if (owner == t).any()]
    spill.close()
    return floors, tiles


@pytest.mark.parametrize("seed", [0, 1])
def test_tiled_limiter_gives_the_whole_limiter_bits(tmp_path, seed):
    """Given the same height field and triangles, every tile's limited gradients are the
    whole-survey limiter's to the bit, its noise floors the whole survey's medians, its
    directions the same lines; tiles are small (a few hundred points), so most vertices
    have a neighbour or a 2-ring vertex in another tile."""
    rng = np.random.default_rng(seed)
    n = 6000
    xy = rng.uniform(0, 100, (n, 2))
    z = np.sin(xy[:, 0] / 9) * np.cos(xy[:, 1] / 13) * 5 + rng.normal(0, 0.05, n)
    gradients = np.column_stack([np.cos(xy[:, 0] / 9) * np.cos(xy[:, 1] / 13) * 5 / 9,
                                 -np.sin(xy[:, 0] / 9) * np.sin(xy[:, 1] / 13) * 5 / 13])
    gradients += rng.normal(0, 0.2, (n, 2))
    triangles, _ = trim(xy, delaunay(xy), max_edge="auto", min_circle_ratio=0.0)
    used = np.unique(triangles)
    xy, z, gradients, triangles = xy[used], z[used], gradients[used], np.searchsorted(used, triangles)
    whole_values, whole_gradients, whole_directions, report = control_overshoot(xy, z, gradients, triangles)
    assert report.gradients_limited > 1000 and report.directions_changed > 100
    assert report.heights_reconciled > 20
    edges = edge_table(triangles, len(xy)).edges
    a, b = edges[:, 0], edges[:, 1]
    residual = np.abs(z[b] - z[a] - 0.5 * (np.einsum("ij,ij->i", gradients[a] + gradients[b], xy[b] - xy[a])))
    floors, tiles = _tiled_limiter(xy, z, gradients, triangles, 6, tmp_path)
    assert np.isclose(floors.first, np.median(residual), rtol=1e-12, atol=0)
    seen = np.zeros(len(xy), dtype=bool)
    for limits, own in tiles:
        corners = limits.records["index"]
        assert np.array_equal(limits.gradients, whole_gradients[corners])        # bits
        assert np.array_equal(limits.records["z"], whole_values[corners])
        local_edges = corners[edge_table(limits.triangles, len(corners)).edges]
        at = np.searchsorted(edges[:, 0] * len(xy) + edges[:, 1], local_edges[:, 0] * len(xy) + local_edges[:, 1])
        assert np.array_equal(edges[at], local_edges)
        whole = whole_directions[at]
        cross = limits.directions[:, 0] * whole[:, 1] - limits.directions[:, 1] * whole[:, 0]
        assert np.abs(cross).max() <= 1e-15 * np.abs(whole).max()                 # the same lines
        assert np.array_equal(np.sort(corners[limits.triangles], axis=1), np.sort(own, axis=1))
        seen[corners] = True
    assert seen.all()
    # each vertex counted by the tile of its cell, each edge by that of its lower end: the
    # tiles' counts add up to the whole limiter's
    assert sum(limits.limited for limits, _ in tiles) == report.gradients_limited
    assert sum(limits.turned for limits, _ in tiles) == report.directions_changed
    assert sum(limits.lifted for limits, _ in tiles) == report.heights_reconciled


def test_cli_fits_in_tiles_beyond_memory(tmp_path):
    source = tmp_path / "terrain.las"
    write_terrain_las(source, 24000)
    whole, _, _ = _in_memory(source, [2], 2)
    args = ["fit", "--smooth", "off", str(source), "--classes", "2", "-o", str(tmp_path / "out.ply"), "--level", "2",
            "--memory", "1M"]
    for option in (["--normals", "file"],):
        refused = CliRunner().invoke(main, args + option)
        assert refused.exit_code == 1
        assert " ".join(option) in refused.output and "terrain.las" in refused.output
        assert not (tmp_path / "out.ply").exists()
    result = CliRunner().invoke(main, args + ["--report", str(tmp_path / "r.json")])   # the limiter on
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["tiles"] == 4      # 24000 points, >= 10000 a tile
    assert report["overshoot"]["gradients_limited"] == whole.limiter["gradients_limited"] > 0
    _assert_same_mesh(tmp_path / "out.ply", whole)


def test_the_library_fit_runs_in_tiles_beyond_its_memory_as_the_cli_does(tmp_path):
    """c1mesh.fit is the CLI's one driver: a LAS beyond FitOptions(memory="1M") (a size, as
    --memory takes it) is fitted in tiles, not refused, and writes the CLI's bytes."""
    import c1mesh

    source = tmp_path / "terrain.las"
    write_terrain_las(source, 24000)
    result = c1mesh.fit(str(source), tmp_path / "api.ply", FitOptions(smooth="off", classes=(2,), level=2, memory="1M"))
    assert result.mesh is None and result.report["tiles"] == 4
    cli = CliRunner().invoke(main, ["fit", "--smooth", "off", str(source), "--classes", "2", "-o", str(tmp_path / "cli.ply"),
                                    "--level", "2", "--memory", "1M"])
    assert cli.exit_code == 0, cli.output
    assert (tmp_path / "api.ply").read_bytes() == (tmp_path / "cli.ply").read_bytes()


def test_a_las_file_named_otherwise_is_fitted_in_tiles_and_a_las_stream_is_refused_with_the_reason(tmp_path):
    """read_cloud reads a LAS/LAZ file by --input-format, or a COPC file by its .copc name;
    the tiled fit took only .las/.laz names, so these were read whole and refused beyond
    --memory with 'only LAS/LAZ inputs are fitted in tiles ... convert it to LAS/LAZ'.
    Now they are fitted in tiles as the .las is; a LAS stream (stdin), which the tiled fit
    cannot reread, is refused with that reason instead."""
    source = tmp_path / "terrain.las"
    write_terrain_las(source, 8000)
    args = ["--classes", "2", "--level", "1", "--memory", "5M"]
    expected = tmp_path / "las.ply"
    assert CliRunner().invoke(main, ["fit", "--smooth", "off", str(source), "-o", str(expected), *args]).exit_code == 0
    for name, fmt in (("terrain.dat", ["--input-format", "las"]), ("terrain.copc", [])):
        renamed = tmp_path / name
        renamed.write_bytes(source.read_bytes())
        out = tmp_path / (name + ".ply")
        result = CliRunner().invoke(main, ["fit", "--smooth", "off", str(renamed), "-o", str(out), *fmt, *args])
        assert result.exit_code == 0, result.output
        assert out.read_bytes() == expected.read_bytes()
    streamed = subprocess.run([sys.executable, "-m", "c1mesh.cli", "fit", "-", "--input-format", "las", "-o",
                               str(tmp_path / "s.ply"), *args], input=source.read_bytes(), capture_output=True,
                              timeout=120)
    assert streamed.returncode == 1 and not (tmp_path / "s.ply").exists()
    message = streamed.stderr.decode()
    assert "not from a stream" in message and "convert it to LAS/LAZ" not in message, message


def test_memory_rule():
    from c1mesh.survey.sizing import grid_side, tiles_at_once

    assert grid_side(2_000_000, 10**9) == 4                  # 138,888 points a tile at most
    assert tiles_at_once(2 * 10**9, 8) == 2                   # half the budget to tiles of 1/4 of it
    assert tiles_at_once(2 * 10**9, 1) == 1
    assert points_per_tile(64 * 10**9) == 1_000_000             # capped: more tiles in flight instead
    assert tiles_at_once(64 * 10**9, 8) == 8
    assert tiles_at_once(64 * 10**9, 64) == 17                  # 32 GB over 1.8 GB a tile
    assert grid_side(2_000_000, 10**9, per_tile=10**6) == 2
    assert fits_in_memory(1_000_000, 2 * 10**9)
    assert not fits_in_memory(12_000_000, 2 * 10**9)
    assert fits_in_memory(10**9, None)
    assert points_per_tile(2 * 10**9) * 1_800 * 4 <= 2 * 10**9


def test_peel_takes_thin_components_that_reach_the_boundary():
    """A chain of three thin triangles with one on the boundary goes whole; a thin triangle
    inside, touching the chain only at a corner, stays (trim's rule: through edges)."""
    chain = np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4], [4, 10, 11], [20, 21, 22]])
    boundary = np.array([False, False, True, False, False])
    assert peeled(chain, boundary).tolist() == [True, True, True, False, False]
    assert not peeled(chain, np.zeros(5, bool)).any()
    kept = drop_triangles(np.array([[9, 8, 7], [3, 1, 2], [1, 2, 10]]), np.array([[2, 3, 1]]))
    assert kept.tolist() == [[9, 8, 7], [1, 2, 10]]


def test_halo_lookups_equal_sets_of_corners():
    """kept_triangles (a hash of the removed triangles) and triangles_among (a hash of a
    halo's survey numbers and its filter) against Python sets and dicts on random small
    triangle lists, removed rows given in any corner order, triangles in one array or in
    parts."""
    rng = np.random.default_rng(1)
    for _ in range(200):
        n, count = int(rng.integers(5, 60)), int(rng.integers(0, 80))
        tri = np.array([rng.choice(n, 3, replace=False) for _ in range(count)], dtype=np.int64).reshape(-1, 3)
        removed = np.array([rng.permutation(tri[rng.integers(count)]) if count and rng.random() < 0.6
                            else rng.choice(n, 3, replace=False) for _ in range(rng.integers(0, 30))],
                           dtype=np.int64).reshape(-1, 3)
        gone = {tuple(sorted(row)) for row in removed.tolist()}
        assert kept_triangles(tri, removed).tolist() == [tuple(sorted(row)) not in gone for row in tri.tolist()]
        index = np.sort(rng.choice(n, rng.integers(0, n), replace=False)).astype(np.int64)
        row_of = {v: i for i, v in enumerate(index.tolist())}
        inside = [[row_of[v] for v in row] for row in tri.tolist() if all(v in row_of for v in row)]
        assert triangles_among(index, tri).tolist() == inside
        cut = int(rng.integers(0, count + 1))                  # parts, one hash: their results in turn
        assert triangles_among(index, iter([tri[:cut], tri[cut:], tri[:0]])).tolist() == inside


def test_tiled_fit_carries_crs_and_colours(tmp_path):
    """Autzen ground (a CRS, 8-bit RGB) fitted in tiles through the CLI: the PLY comment,
    the .prj and the report carry the file's CRS as the in-memory fit does; every output
    vertex at an input point has that point's colour (the file is the ground truth), and
    vertices both fits write have the same colour to one step (blending rounds)."""
    from c1mesh.formats import read_cloud

    source = SAMPLES / "autzen_trim.laz"
    base = ["fit", "--smooth", "off", str(source), "--classes", "2", "--level", "2", "--normals", "estimate",
            "--gradients", "normals"]                  # the tiled fit's gradients
    whole = CliRunner().invoke(main, base + ["-o", str(tmp_path / "whole.ply"), "--report", str(tmp_path / "w.json")])
    tiled = CliRunner().invoke(main, base + ["-o", str(tmp_path / "tiled.ply"), "--report", str(tmp_path / "t.json"),
                                             "--memory", "2M"])
    assert whole.exit_code == 0 and tiled.exit_code == 0, whole.output + tiled.output
    report = json.loads((tmp_path / "t.json").read_text())
    assert report["tiles"] == 4 and report["crs"]["source"] == "file"
    assert report["crs"] == json.loads((tmp_path / "w.json").read_text())["crs"]
    assert (tmp_path / "tiled.prj").read_text() == (tmp_path / "whole.prj").read_text()
    a, b = read_cloud(tmp_path / "whole.ply"), read_cloud(tmp_path / "tiled.ply")
    assert a.crs == b.crs is not None
    assert b.colors is not None and len(np.unique(b.colors, axis=0)) > 100

    def keys(xyz, decimals=6):
        return [tuple(row) for row in np.round(xyz, decimals).tolist()]
    las = laspy.read(str(source))
    ground = np.asarray(las.classification) == 2
    truth = dict(zip(keys(np.column_stack([las.x, las.y, las.z])[ground]),
                     np.column_stack([las.red, las.green, las.blue])[ground].tolist()))
    at_points = [(i, truth[k]) for i, k in enumerate(keys(b.points)) if k in truth]
    assert len(at_points) > 20000
    rows, colours = zip(*at_points)
    assert np.array_equal(b.colors[list(rows)], np.asarray(colours))
    whole_colour = dict(zip(keys(a.points, 3), a.colors.tolist()))      # refined points: to rounding
    common = [(i, whole_colour[k]) for i, k in enumerate(keys(b.points, 3)) if k in whole_colour]
    assert len(common) > 0.95 * len(b.points)
    rows, colours = zip(*common)
    assert np.abs(b.colors[list(rows)].astype(int) - np.asarray(colours)).max() <= 1


def _west_east_survey(tmp_path):
    """A synthetic LAS of 24,000 points (terrain.las) and its west and east halves (at the
    median x) as two LAS files: (whole path, [west path, east path], the LasData, west mask)."""
    whole_file = tmp_path / "terrain.las"
    write_terrain_las(whole_file, 24000)
    las = laspy.read(str(whole_file))
    west = np.asarray(las.x) < np.median(np.asarray(las.x))
    parts = []
    for name, mask in (("west.las", west), ("east.las", ~west)):
        part = laspy.LasData(las.header)
        part.points = las.points[mask]
        parts.append(tmp_path / name)
        part.write(str(parts[-1]))
    return whole_file, parts, las, west


def test_seamless_survey_beyond_memory_is_the_tiled_fit_of_its_concatenation(tmp_path):
    """`fit A.las B.las --seamless -o` with a survey larger than --memory allows: the files
    are read one after another as one survey by the memory-bounded fit, which writes what
    it writes for the concatenated file (the same bytes, compared), and matches the
    in-memory fit of the whole cloud as the tiled fit does. With -O the same fit is split
    by the ownership rule: each input's mesh is the in-memory `--seamless -O` mesh of that
    input (to rounding), and merging the outputs' exactly equal vertices gives the -o mesh
    (the border vertices are the same bits in both outputs)."""
    whole_file, parts, las, west = _west_east_survey(tmp_path)
    concatenated = laspy.LasData(las.header)
    concatenated.points = las.points[np.argsort(~west, kind="stable")]
    concatenated.write(str(tmp_path / "concatenated.las"))
    args = ["--classes", "2", "--level", "2", "--memory", "1M"]
    survey = CliRunner().invoke(main, ["fit", "--smooth", "off", *map(str, parts), "--seamless", "-o", str(tmp_path / "survey.ply"),
                                       "--report", str(tmp_path / "survey.json"), *args])
    assert survey.exit_code == 0, survey.output
    single = CliRunner().invoke(main, ["fit", "--smooth", "off", str(tmp_path / "concatenated.las"), "-o",
                                       str(tmp_path / "single.ply"), *args])
    assert single.exit_code == 0, single.output
    report = json.loads((tmp_path / "survey.json").read_text())
    assert report["tiles"] == 4 and report["input"] == [str(p) for p in parts]
    assert (tmp_path / "survey.ply").read_bytes() == (tmp_path / "single.ply").read_bytes()
    whole, _, _ = _in_memory(whole_file, [2], 2)
    _assert_same_mesh(tmp_path / "survey.ply", whole)
    split = CliRunner().invoke(main, ["fit", "--smooth", "off", *map(str, parts), "--seamless", "-O", str(tmp_path / "out"),
                                      "--report", str(tmp_path / "split.json"), *args])
    assert split.exit_code == 0, split.output
    assert json.loads((tmp_path / "split.json").read_text())["tiles"] == 4      # the tiled fit ran
    memory = CliRunner().invoke(main, ["fit", "--smooth", "off", *map(str, parts), "--seamless", "-O", str(tmp_path / "mem"),
                                       *args[:-2]])
    assert memory.exit_code == 0, memory.output
    outputs = [tmp_path / "out" / f"{p.stem}.c1.ply" for p in parts]       # named as in batch mode
    for tiled_output in outputs:
        assert len(trimesh.load(tiled_output, process=False).faces) > 10000          # each input owns a part
        _assert_same_mesh(tiled_output, trimesh.load(tmp_path / "mem" / tiled_output.name, process=False))
    _assert_exact_merge(outputs, tmp_path / "survey.ply")


def test_curtain_noise_floor_is_the_exact_median_over_every_edge_once():
    """curtains.noise_floor: np.median of |trapezoid residual| over the edge table's
    edges (each once), whatever the triangles' order and orientation, so tiles can find
    it by a streamed median of their own edges."""
    from c1mesh.stages.curtains import noise_floor
    from c1mesh.stages.limiter import trapezoid_residuals

    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 50, (3000, 2))
    z = np.sin(xy[:, 0] / 7) + rng.normal(0, 0.05, len(xy))
    gradients = np.column_stack([np.cos(xy[:, 0] / 7) / 7, np.zeros(len(xy))])
    triangles = delaunay(xy)
    edges = edge_table(triangles, len(xy)).edges
    expected = np.median(np.abs(trapezoid_residuals(xy, z, gradients, edges)))
    assert noise_floor(xy, z, gradients, triangles) == expected
    shuffled = triangles[rng.permutation(len(triangles))][:, ::-1]
    assert noise_floor(xy, z, gradients, shuffled) == expected


def _tile_rows_agree(report, level):
    """The report's per-tile rows against the fit's own totals: one row per tile, every
    tile's height-field points and owned triangles counted once (the faces are L^2 per
    base triangle), every tile with a worker and its seconds."""
    rows = report["tile_tasks"]
    assert [r["tile"] for r in rows] == list(range(report["tiles"]))
    assert sum(r["triangles"] for r in rows) * level * level == report["output_mesh"]["faces"]
    assert report["points"]["kept"] <= sum(r["points"] for r in rows) <= report["points"]["read"]
    assert all(r["worker"] and r["seconds"] > 0 for r in rows if r["triangles"])
    return {p["worker"] for r in rows for p in r["passes"].values()}


def test_tiled_fit_writes_the_same_bytes_wherever_its_tiles_run(tmp_path):
    """The tile tasks (normals, triangulation, refinement) in this process, on a pool of
    two processes (-j 2) and on a Dask LocalCluster of two workers (--scheduler) write
    the same file, byte for byte; the report names the workers that ran each tile."""
    distributed = pytest.importorskip("distributed")
    source = tmp_path / "terrain.las"
    write_terrain_las(source, 4000, seed=3)
    options = FitOptions(smooth="off", classes=[2], level=2)
    here = fit(source, tmp_path / "here.ply", replace(options, memory=10**9), tiles=TiledRun(per_tile=450)).report
    assert here["tiles"] == 9
    pool = fit(source, tmp_path / "pool.ply", replace(options, memory=10**9), tiles=TiledRun(per_tile=450, jobs=2)).report
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        dask = fit(source, tmp_path / "dask.ply", replace(options, memory=10**9), tiles=TiledRun(per_tile=450, scheduler=cluster.scheduler_address)).report
        dask_workers = set(cluster.scheduler.workers)
    expected = (tmp_path / "here.ply").read_bytes()
    assert (tmp_path / "pool.ply").read_bytes() == expected
    assert (tmp_path / "dask.ply").read_bytes() == expected
    here_workers, pool_workers = _tile_rows_agree(here, 2), _tile_rows_agree(pool, 2)
    assert _tile_rows_agree(dask, 2) == dask_workers and len(dask_workers) == 2
    assert len(here_workers) == 1 and len(pool_workers) == 2 and not here_workers & pool_workers
    assert [r["triangles"] for r in pool["tile_tasks"]] == [r["triangles"] for r in here["tile_tasks"]]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dask.ply", "here.ply", "pool.ply", "terrain.las"]


def _big_las(tmp_path):
    """A LAS the CLI fits in 4 tiles under --memory 1M, and the arguments that do so."""
    source = tmp_path / "terrain.las"
    write_terrain_las(source, 12000, seed=5)
    return source, ["fit", "--smooth", "off", str(source), "--classes", "2", "--level", "1", "--memory", "1M"]


def _every_job_at_once(monkeypatch):
    """Let -j N run N tile tasks at once under the tiny budgets of these tests (the budget's
    own rule, tiles_at_once, is tested in test_memory_rule)."""
    import c1mesh.pipeline.bounded_fit as bounded_fit

    monkeypatch.setattr(bounded_fit, "tiles_at_once", lambda memory, jobs, per_point=None: jobs)


def test_cli_runs_tiles_on_jobs(tmp_path, monkeypatch):
    """`fit BIG.las --memory 1M -j 2` fits in tiles on two processes and writes what one
    process writes: the tiles come from the budget, not from the number of jobs."""
    _every_job_at_once(monkeypatch)
    source, args = _big_las(tmp_path)
    one = CliRunner().invoke(main, args + ["-o", str(tmp_path / "one.ply"), "-j", "1"])
    two = CliRunner().invoke(main, args + ["-o", str(tmp_path / "two.ply"), "-j", "2",
                                           "--report", str(tmp_path / "two.json")])
    assert one.exit_code == 0 and two.exit_code == 0, one.output + two.output
    assert (tmp_path / "one.ply").read_bytes() == (tmp_path / "two.ply").read_bytes()
    report = json.loads((tmp_path / "two.json").read_text())
    assert report["scheduler"] == "2 local processes"
    assert len(_tile_rows_agree(report, 1)) == 2


def test_cli_runs_tiles_on_one_process_per_thread_by_default(tmp_path, monkeypatch):
    """Without -j a fit larger than --memory runs its tiles on one local process per
    thread of --threads (as many as the budget allows), and in this process at
    --threads 1; the bytes are those of -j 1."""
    _every_job_at_once(monkeypatch)
    source, args = _big_las(tmp_path)
    runs = {}
    for threads in ("1", "2"):
        result = CliRunner().invoke(main, args + ["-o", str(tmp_path / f"t{threads}.ply"), "--threads", threads,
                                                  "--report", str(tmp_path / f"t{threads}.json")])
        assert result.exit_code == 0, result.output
        runs[threads] = json.loads((tmp_path / f"t{threads}.json").read_text())["scheduler"]
    assert runs == {"1": "in process", "2": "2 local processes"}
    assert (tmp_path / "t1.ply").read_bytes() == (tmp_path / "t2.ply").read_bytes()


def test_cli_stops_at_a_failing_tile(tmp_path, monkeypatch):
    """A tile whose task fails stops the fit with exit 1, one line naming the tile, and
    no output (in this process and on a pool of two)."""
    import c1mesh.survey.height_runs as height_runs
    import c1mesh.survey.refine_runs as refine_runs

    _every_job_at_once(monkeypatch)
    source, args = _big_las(tmp_path)
    real = refine_runs._refine_tile

    def failing(job, t, part):
        if t == 2:
            raise ValueError("no good")
        return real(job, t, part)
    monkeypatch.setattr(refine_runs, "_refine_tile", failing)
    here = CliRunner().invoke(main, args + ["-o", str(tmp_path / "failed.ply"), "-j", "1"])
    assert here.exit_code == 1
    assert here.output.startswith(f"c1mesh: error: {source}: tile 2 (cell ") and here.output.endswith(": no good\n")
    assert here.output.count("\n") == 1
    monkeypatch.setattr(refine_runs, "_refine_tile", height_runs._position_tile)   # fails on every worker
    pool = CliRunner().invoke(main, args + ["-o", str(tmp_path / "failed.ply"), "-j", "2"])
    assert pool.exit_code == 1 and pool.output.startswith(f"c1mesh: error: {source}: tile ")
    assert "RefineJob" in pool.output and pool.output.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["terrain.las"]


@pytest.mark.slow
def test_cli_sends_tiles_to_a_scheduler(tmp_path):
    """`fit BIG.las --memory 1M --scheduler ADDR -o out.ply` runs the tiles on the cluster
    (both workers named in the report) and writes what a local run writes; an input that
    fits in memory is fitted here, with a note that the scheduler was not used."""
    distributed = pytest.importorskip("distributed")
    source, args = _big_las(tmp_path)
    here = CliRunner().invoke(main, args + ["-o", str(tmp_path / "here.ply")])
    assert here.exit_code == 0, here.output
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        sent = CliRunner().invoke(main, args + ["-o", str(tmp_path / "dask.ply"), "--scheduler",
                                                cluster.scheduler_address, "--report", str(tmp_path / "r.json")])
        small = CliRunner().invoke(main, args[:-2] + ["-o", str(tmp_path / "small.ply"), "--scheduler",
                                                      cluster.scheduler_address])
        workers = set(cluster.scheduler.workers)
    assert sent.exit_code == 0, sent.output
    assert (tmp_path / "dask.ply").read_bytes() == (tmp_path / "here.ply").read_bytes()
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["scheduler"] == cluster.scheduler_address
    assert _tile_rows_agree(report, 1) == workers and len(workers) == 2
    assert small.exit_code == 0, small.output                # fitted here, with one note
    assert small.output.startswith("c1mesh: note: ") and "--scheduler not used" in small.output
    assert (tmp_path / "small.ply").exists()


@pytest.mark.slow
def test_real_dask_scheduler_and_two_workers_fit_the_tiles(tmp_path, dask_processes):
    """`dask scheduler` + two `dask worker` processes on 127.0.0.1 (they share this file
    system, as the spill needs), then `fit BIG.las --memory 1M --scheduler`: the bytes of a
    local run, both workers in the report."""
    source, args = _big_las(tmp_path)
    here = CliRunner().invoke(main, args + ["-o", str(tmp_path / "here.ply")])
    sent = CliRunner().invoke(main, args + ["-o", str(tmp_path / "cluster.ply"), "--scheduler", dask_processes,
                                            "--report", str(tmp_path / "r.json")])
    assert here.exit_code == 0 and sent.exit_code == 0, here.output + sent.output
    assert (tmp_path / "cluster.ply").read_bytes() == (tmp_path / "here.ply").read_bytes()
    workers = _tile_rows_agree(json.loads((tmp_path / "r.json").read_text()), 1)
    assert len(workers) == 2 and all(w.startswith("tcp://127.0.0.1:") for w in workers)


def test_fits_in_tiles_show_their_tiles_on_a_terminal_and_nothing_on_a_pipe(tmp_path):
    """A fit larger than --memory, of one file or of a `--seamless -O` survey: on a
    terminal the progress bar names each stage and counts each pass's tiles as they
    finish, not only the outputs once everything is done; on a pipe stderr stays empty."""
    whole_file, parts, _, _ = _west_east_survey(tmp_path)
    args = ["fit", "--smooth", "off", *map(str, parts), "--seamless", "--classes", "2", "--level", "2", "--memory", "1M"]
    shown = stderr_on_a_terminal([*args, "-O", str(tmp_path / "tty")])
    for stage in ("normals: tile 4 of 4", "triangulate: tile 4 of 4", "refine: tile 4 of 4", "refine+write"):
        assert stage in shown, shown
    assert sorted(p.name for p in (tmp_path / "tty").iterdir()) == ["east.c1.ply", "west.c1.ply"]
    single = stderr_on_a_terminal(["fit", "--smooth", "off", str(whole_file), "-o", str(tmp_path / "single.ply"), *args[-6:]])
    assert "normals: tile 4 of 4" in single and "refine: tile 4 of 4" in single, single
    piped = subprocess.run([sys.executable, "-m", "c1mesh.cli", *args, "-O", str(tmp_path / "pipe")],
                           capture_output=True, text=True, timeout=300)
    assert piped.returncode == 0 and piped.stderr == "", piped.stderr


def test_a_mesh_level_from_resolution_in_tiles_is_the_whole_fits(tmp_path):
    """--resolution of a mesh beyond --memory: the level whose mean output edge is nearest
    R (geo.products.level_for_edge), from the tiles' own triangles' side lengths added up.
    Truth: the mean side of the whole fit's triangulation (its level-1 mesh), by a plain
    loop over its faces, rounded; and the tiled mesh is the whole fit's at that level."""
    source = SAMPLES / "4_6_crop.las"
    triangulation, _, _ = _in_memory(source, [2], 1)
    sides = [np.linalg.norm(triangulation.vertices[face[k], :2] - triangulation.vertices[face[(k + 1) % 3], :2])
             for face in triangulation.faces for k in range(3)]
    resolution = float(np.mean(sides)) / 2.6           # between levels 2 and 3: level 3
    expected = int(round(np.mean(sides) / resolution))
    assert expected == 3
    whole, _, _ = _in_memory(source, [2], expected)
    options = FitOptions(smooth="off", classes=(2,), resolution=resolution, memory=10**9)
    report = fit(source, tmp_path / "tiled.ply", options, tiles=TiledRun(per_tile=1000)).report
    assert report["tiles"] == 16
    assert report["level"] == expected and report["level_from"] == "resolution"
    assert report["resolution"] == resolution
    _assert_same_mesh(tmp_path / "tiled.ply", whole)
    memory = fit(source, tmp_path / "whole.ply", replace(options, memory=None)).report
    assert memory["level"] == expected and memory["level_from"] == "resolution"
    assert memory["resolution"] == resolution


def test_the_first_noise_floor_takes_the_curtains_summaries_without_the_removed_edges(tmp_path, monkeypatch):
    """The limiter's first floor takes each tile's curtains' floor summary without the
    edges only removed triangles held (halos.KeptSummaries, limiter.floor_summary_after):
    on Autzen ground in 16 tiles the curtains remove triangles in some tiles, and the
    floors and the mesh equal those found with every summary written afresh, bit for bit.
    (The default run has the same case against the in-memory fit,
    test_tiled_fit_of_autzen_ground_removes_the_bowties_and_curtains_of_the_whole_fit,
    whose mesh a stale summary moves by up to 6e-5 ft.)"""
    import c1mesh.survey.halos as halos

    shrunk = []
    after = halos.floor_summary_after

    def spy(tile, earlier, removed):
        summary = after(tile, earlier, removed)
        shrunk.append(len(earlier) - len(summary))
        return summary
    monkeypatch.setattr(halos, "floor_summary_after", spy)
    options = replace(FitOptions(smooth="off", classes=(2,), level=1), memory=10**9)
    source = SAMPLES / "autzen_trim.laz"
    taken = fit(source, tmp_path / "a.ply", options, tiles=TiledRun(per_tile=1700)).report
    assert taken["tiles"] == 16 and sum(shrunk) > 0                # some tiles lost edges
    floor_files = halos.floor_files
    monkeypatch.setattr(halos, "floor_files", lambda halos_, temps, label, first=None, runner=None, name=str,
                        kept=None, reconciled=None: floor_files(halos_, temps, label, first, runner, name,
                                                                None, reconciled))
    calls = len(shrunk)
    fresh = fit(source, tmp_path / "b.ply", options, tiles=TiledRun(per_tile=1700)).report
    assert len(shrunk) == calls                                     # every summary written afresh
    assert taken["overshoot"]["noise_floors"] == fresh["overshoot"]["noise_floors"]
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()


@pytest.mark.parametrize("turn", [0, 30])
def test_a_gridded_las_in_tiles_is_the_in_memory_fit(tmp_path, turn):
    """A 0.5 m grid (an exported DEM) with a hole and millimetre coordinates near the
    origin, along the axes (every square's corners cocircular) or turned by 30 degrees
    (nearly cocircular, borders nearly straight): the tiles triangulate and cut ties as
    the whole fit does, so the tiled mesh is the in-memory one (both grids used to be
    refused as "not edge-manifold")."""
    u, v = (w.ravel() for w in np.meshgrid(np.arange(0, 60, 0.5), np.arange(0, 45, 0.5)))
    c, s = np.cos(np.radians(turn)), np.sin(np.radians(turn))
    x, y = c * u - s * v, s * u + c * v
    keep = np.hypot(u - 25, v - 20) > 6
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [0.001] * 3, [0, 0, 0]
    record = laspy.ScaleAwarePointRecord.zeros(int(keep.sum()), header=header)
    record.x, record.y = x[keep], y[keep]
    record.z = 10 + 3 * np.sin(x[keep] / 17) * np.cos(y[keep] / 23)
    record.classification = np.full(int(keep.sum()), 2, np.uint8)
    source = tmp_path / "grid.las"
    with laspy.open(str(source), mode="w", header=header) as writer:
        writer.write_points(record)
    options = FitOptions(level=2, smooth="off")
    report = fit(source, tmp_path / "tiled.ply", replace(options, memory=10**9), tiles=TiledRun(per_tile=1500)).report
    assert report["tiles"] >= 4
    fit(source, tmp_path / "whole.ply", options)
    _assert_same_mesh(tmp_path / "tiled.ply", trimesh.load(tmp_path / "whole.ply", process=False, force="mesh"))


def test_without_max_edge_a_tile_that_must_read_past_the_budget_is_refused(tmp_path):
    """--max-edge none keeps the survey's hull slivers until the peel, and certifying them
    makes a border tile read most of the border (60k uniform points: 44k). Past what
    --memory allows a read (TILE_SHARE tiles' points) that is one line naming the file
    and the option, exit 1, nothing written, instead of a read the budget cannot hold."""
    source = tmp_path / "t.las"
    write_terrain_las(source, 60000)
    result = CliRunner().invoke(main, ["fit", str(source), "-o", str(tmp_path / "x.ply"), "--max-edge", "none",
                                       "--memory", "40M", "--level", "1", "--smooth", "off"])
    assert result.exit_code == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and str(source) in lines[0] and "--max-edge" in lines[0] and "--memory" in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.las"]


def test_a_local_pool_starts_under_a_deep_temporary_folder(tmp_path, monkeypatch):
    """The forkserver's Unix socket lives in the temporary folder, and a socket's path has
    at most 104 bytes: under a deep $TMPDIR (a CI job's scratch folder) the pool starts its
    workers by "spawn" instead of failing with "AF_UNIX path too long"."""
    import tempfile

    from c1mesh.survey.distributed import TaskRunner, pool_start_method

    deep = tmp_path / ("d" * 60) / ("e" * 40)
    deep.mkdir(parents=True)
    monkeypatch.setenv("TMPDIR", str(deep))
    monkeypatch.setattr(tempfile, "tempdir", None)
    assert pool_start_method("forkserver") == "spawn" and pool_start_method(None) is None
    with TaskRunner(jobs=2) as runner:
        assert sorted(runner.map(abs, 4, lambda i: (-i,), str)) == [(0, 0), (1, 1), (2, 2), (3, 3)]
    monkeypatch.setenv("TMPDIR", "/tmp")
    monkeypatch.setattr(tempfile, "tempdir", None)
    assert pool_start_method("forkserver") == "forkserver"
