"""Curtains in the axis frame: triangles that hang along the height axis, fold against their
data, or are thinner than the data's noise.

A height field over a plane sees the scan along the plane's axis e3, as a depth camera sees
it along its rays (a parallel projection instead of a central one). Where the surface is
not a graph over the plane (a silhouette the surface curves past, an ear in front of the
head, two layers of points), the Delaunay triangulation in (x, y) joins points across the
gap with triangles that hang nearly parallel to e3 — curtains. Seen from above they are
the black streaks and folded specks of issue 10; issue 11's rule for depth jumps, "holes,
not curtains", applies to them as well. A triangle is dropped as

* "shadow_edge": one of its edges runs within `SHADOW_ANGLE` of e3 (grid.depth_jumps' rule,
  PCL's shadow angle, with e3 as the view ray);
* "grazing": its plane's normal is more than `GRAZING_ANGLE` from e3 (seen edge-on);
* "facing_away": its plane's normal is more than 90° from the data normal of one of its
  corners (both taken on the axis side, normal signs are not trusted). The linear
  triangle is then already folded against its data, by the measure of
  quality.folded_faces: the points it joins belong to surface patches that face apart
  (the front and the back of a silhouette, a point from another layer), and any
  interpolant of those normals over it turns by more than 90° inside it;
* "thinner_than_noise": its width in the plane (twice its area over its longest edge) is
  below the noise floor of the heights (the median |trapezoid residual| of the
  triangulation's edges, c1mesh.stages.limiter's measure of noise). The heights then set the
  slope across it only to within more than 1 (45°), and the spline, which interpolates
  them exactly, turns by that much across a sliver narrower than the noise: on the bunny
  two 0.5 mm wide slivers (noise floor 1.0 mm) held the last folded faces.

All four are properties of the input triangle and its data, not of the spline, so exact
data of a height field over the plane whose slopes are below tan(90° - GRAZING_ANGLE) and
whose curvature the triangles resolve lose nothing (their noise floor is an O(h³)
residual, below the width of all but degenerate triangles; tested on the analytic
samples). Holes are left where curtains were; the trim then peels the slivers and bowties
the holes expose (trim.retrim_run), so the result keeps trim's guarantees (edge-manifold,
no bowtie vertex).

Like the trim, the rule is a function of a tile (`curtains_and_bowties`, trim.TrimTile) given the
noise floor, and `remove_curtain_run` runs it and the re-trim over a trim.TrimRun's tiles:
the in-memory fit's one (`remove_curtains`) or a survey's (c1mesh.survey.trim_runs).

The first three rules take e3 as a view ray: they find what a scanner looking along e3
cannot have seen as a graph. Aerial LiDAR ground (LAS/LAZ points of the bare-earth classes
`GROUND_CLASSES`, selected with --classes, heights along world z) is a height field by the
format's definition: the classifier kept one return per place, the last one from above, so
a steep triangle there is a steep bank or a ditch wall, not a curtain, and removing it
opens a hole inside the data (issue 21: on a 0.93 m ground tile, 101 of 483 removed
triangles were shadow_edge, facing_away or grazing, and their cells lost their DEM
values). `view_rules` says whether they run; "thinner_than_noise" is a property of the
spline on any data (it divides by the triangle's width) and always runs, as do trim's
long_edge, sliver and bowtie rules.
"""
from __future__ import annotations

from dataclasses import replace
from functools import partial

import numpy as np

from c1mesh.core.threads import parallel_blocks
from c1mesh.core.tile import Tile
from c1mesh.stages import _curtains as kernel
from c1mesh.stages.grid import GRAZING_ANGLE, SHADOW_ANGLE
from c1mesh.stages.limiter import floor_summary, reduce_floor, residual_sizes, trapezoid_residuals
from c1mesh.stages.trim import (MIN_CIRCLE_RATIO, Cuts, OneTile, Thin, TrimmedMesh, TrimRun, TrimTile,
                                bowtie_cuts, retrim_run, used_points)

REASONS = ("shadow_edge", "grazing", "facing_away", "thinner_than_noise")
"""Why a triangle is a curtain, in the order the rules are applied (a triangle counts once)."""
VIEW_REASONS = ("shadow_edge", "grazing", "facing_away")
"""The rules that take the height axis as a view ray (skipped on aerial ground)."""
KERNEL_BLOCK = 1 << 14
"""Triangles per block of the kernels (stages/_curtains.pyx), run in the thread
knob's threads (core.threads.parallel_blocks; Python threads, not OpenMP, whose thread pool
does not survive a fork: a forked --jobs worker would hang in it)."""
GROUND_CLASSES = (2, 8, 9, 11)
"""ASPRS LAS classes of surfaces seen from above: ground, model key-point (a subset of
ground in LAS 1.0-1.3), water, road surface."""


def view_rules_apply(classes, axes) -> bool:
    """Whether the view-dependent curtain rules (VIEW_REASONS) run: not on aerial ground,
    that is when the fit keeps only LAS classes of GROUND_CLASSES (classes: the --classes
    tuple, None for all points) and the height axis is world z (axes (3, 3): the frame's
    rows, e3 last). Decided from the options and the frame alone, so the in-memory and the
    tiled fit decide alike."""
    ground = isinstance(classes, (tuple, list)) and bool(classes) and all(int(c) in GROUND_CLASSES for c in classes)
    world_z = np.allclose(np.asarray(axes, dtype=float)[2], (0.0, 0.0, 1.0))
    return not (ground and world_z)


def curtain_triangles(xy: np.ndarray, z: np.ndarray, gradients: np.ndarray, triangles: np.ndarray,
                      shadow_angle: float = SHADOW_ANGLE, grazing_angle: float = GRAZING_ANGLE,
                      floor: float | None = None, view_rules: bool = True) -> dict[str, np.ndarray]:
    """(T,) bool masks of the curtain triangles by reason (each triangle under its first reason,
    in the order of REASONS).

    xy (n, 2), z (n,) and gradients (n, 2) of a height field (height_field.HeightField: local
    coordinates, heights along e3, data gradients ∇z from the normals); triangles (T, 3)
    indices into them. Angles in degrees. Component by component and without square
    roots (squared comparisons), as this runs on every triangle of every fit: a kernel
    (stages/_curtains.pyx) over blocks of KERNEL_BLOCK triangles in the thread knob's threads.
    view_rules=False: the masks of VIEW_REASONS are all False (view_rules_apply).
    """
    if floor is None:                  # a tile passes the survey's (c1mesh.survey.trim_runs)
        floor = noise_floor(xy, z, gradients, triangles)
    return _curtain_masks(point_rows(xy, z, gradients), triangles, shadow_angle, grazing_angle, floor, view_rules)


def _curtain_masks(rows: np.ndarray, triangles: np.ndarray, shadow_angle: float, grazing_angle: float,
                   floor: float, view_rules: bool, alive: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """curtain_triangles over the point rows (n, 5) (`point_rows`); alive (T,) bool: only
    those triangles can be curtains (None: all), so a TrimmedMesh's source needs no copy
    of its kept triangles."""
    tri = np.ascontiguousarray(triangles, dtype=np.int64)
    _check_indices(tri, rows.shape[0])
    live = np.ones(tri.shape[0], dtype=np.uint8) if alive is None else np.ascontiguousarray(alive).view(np.uint8)
    masks = {reason: np.empty(tri.shape[0], dtype=bool) for reason in REASONS}
    cos2 = (np.cos(np.radians(shadow_angle)) ** 2, np.cos(np.radians(grazing_angle)) ** 2)
    flags = [masks[r].view(np.uint8) for r in REASONS]
    parallel_blocks(lambda part: kernel.curtain_masks(rows, tri, live, *cos2, float(floor), view_rules,
                                                      *flags, part.start, part.stop),
                    tri.shape[0], KERNEL_BLOCK)
    return masks


def _check_indices(indices: np.ndarray, n: int) -> None:
    """ValueError unless every point index lies in [0, n): the kernels do not check."""
    if indices.size and (indices.min() < 0 or indices.max() >= n):
        raise ValueError(f"point indices must lie in [0, {n}), got {indices.min()}..{indices.max()}")


def point_rows(xy: np.ndarray, z: np.ndarray, gradients: np.ndarray) -> np.ndarray:
    """(n, 5) float64 rows (x, y, z, gx, gy) of xy (n, 2), z (n,) and gradients (n, 2): the
    kernels' view of the points, one cache line each (they reach them in no order)."""
    rows = np.empty((xy.shape[0], 5))
    rows[:, :2] = xy
    rows[:, 2] = z
    rows[:, 3:] = gradients
    return rows


def record_rows(records: np.ndarray) -> np.ndarray:
    """`point_rows` of core.tile.VERTEX records (m,), field by field (no stacked copies of
    the positions and gradients first)."""
    rows = np.empty((len(records), 5))
    for k, field in enumerate(("x", "y", "z", "gx", "gy")):
        rows[:, k] = records[field]
    return rows


def noise_floor(xy: np.ndarray, z: np.ndarray, gradients: np.ndarray, triangles: np.ndarray) -> float:
    """Median |trapezoid residual| (height units) over every edge of the triangles, each
    edge once: the height noise the data's gradients cannot explain
    (c1mesh.stages.limiter.trapezoid_residuals; O(h³) for exact smooth data).

    The limiter's first noise floor: its floor_summary of the in-memory fit's one tile
    and reduce_floor, so a survey fitted in tiles finds the same floor from its tiles'
    summaries (c1mesh.survey.halos.edge_floor). A TrimmedMesh's floor takes its
    edge table's kept edges instead (`_live_noise_floor`: the same values).
    """
    sizes = floor_summary(Tile.whole(xy, z, gradients, triangles))
    return reduce_floor(lambda: (sizes,))


def _live_noise_floor(xy: np.ndarray, z: np.ndarray, gradients: np.ndarray, mesh: TrimmedMesh) -> float:
    """noise_floor of a TrimmedMesh's kept triangles: the residuals of every edge of its
    edge table, the kept edges' counted (limiter.residual_sizes; without copying the
    (E, 2) edges or building the kept triangles' table)."""
    edges = mesh.table.edges
    return reduce_floor(lambda: (residual_sizes(trapezoid_residuals(xy, z, gradients, edges),
                                                mesh.live_edge_mask()),))


def curtains_and_bowties(tile: TrimTile, floor: float, view_rules: bool = True) -> tuple[Cuts, dict[str, int], Cuts]:
    """The tile's own live triangles that are curtains (curtain_triangles with the noise
    floor `floor`, the survey's; view_rules: view_rules_apply), tile.points the rows of
    `point_rows`, as trim.Cuts with their count by reason; and the bowtie_cuts its own
    vertices have once every curtain it holds is cut (trim.retrim_run's early). The
    curtain rule is a function of one triangle and the floor, so the tile finds the
    curtains of its neighbours' cells that it holds as they do, and with them the whole
    star of each of its vertices after the cut."""
    masks = _curtain_masks(tile.points, tile.source, SHADOW_ANGLE, GRAZING_ANGLE, floor, view_rules,
                           alive=tile.alive)
    cut = np.logical_or.reduce([masks[reason] for reason in REASONS])
    own = tile.own_live()
    after = TrimTile(tile.source, tile.alive & ~cut, tile.size, tile.points, tile.place)
    return (tile.cuts(np.flatnonzero(cut & own)),
            {reason: int(np.count_nonzero(masks[reason] & own)) for reason in REASONS},
            bowtie_cuts(after, tile.cuts(np.flatnonzero(cut))))


def remove_curtain_run(run: TrimRun, floor: float, view_rules: bool = True, thin: Thin | None = None,
                       min_ratio: float = MIN_CIRCLE_RATIO) -> tuple[dict[str, int], dict[str, int]]:
    """The curtains of the run's tiles (noise floor `floor`) and the slivers and bowties
    their holes expose (trim.retrim_run; thin: the run's trim.Thin, None: taken after the
    curtains) removed: (curtains by reason, {"sliver", "bowtie"}). One pass over the tiles
    finds the curtains and the bow-ties their cut leaves (`curtains_and_bowties`)."""
    found = run.map(partial(curtains_and_bowties, floor=floor, view_rules=view_rules))
    counts = {reason: sum(count[reason] for _, count, _ in found) for reason in REASONS}
    return counts, retrim_run(run, Cuts.join([cuts for cuts, _, _ in found]), min_ratio, thin,
                              Cuts.join([early for _, _, early in found]))


def remove_curtains(xy: np.ndarray, z: np.ndarray, gradients: np.ndarray, triangles,
                    trim_report, view_rules: bool = True):
    """Triangles without curtains, and the trim report (trim.TrimReport) with the curtains
    counted by reason in its "removed" (and the slivers and bowties the holes exposed added
    to trim's own counts): remove_curtain_run on the in-memory fit's one tile.

    triangles: the trimmed triangulation, as trim.trim's (T, 3) array or trim.trim_mesh's
    TrimmedMesh (then a TrimmedMesh is returned, and its edges serve the noise floor: no
    sort), so that a triangle trim removes as too long or thin is counted there, not here.
    The holes are then re-trimmed where they are (trim.retrim_run), not the whole mesh again.
    """
    mesh = triangles if isinstance(triangles, TrimmedMesh) else None
    rows = point_rows(xy, z, gradients)
    if mesh is None:
        tri = np.ascontiguousarray(triangles, dtype=np.int64)
        floor = noise_floor(xy, z, gradients, triangles)
        tile = TrimTile(tri, np.ones(tri.shape[0], dtype=bool), xy.shape[0], rows)
    else:              # over the trimmed triangulation, its removed triangles skipped: no copies
        floor = _live_noise_floor(xy, z, gradients, mesh)
        tile = mesh.tile(rows)
    curtains, cleanup = remove_curtain_run(OneTile(tile), floor, view_rules)
    removed = dict(trim_report.removed)
    removed.update(curtains)
    if not any(curtains.values()):
        return triangles, replace(trim_report, removed=removed)
    for reason, count in cleanup.items():
        removed[reason] = removed.get(reason, 0) + count
    used = used_points(tile.source, tile.alive, xy.shape[0])
    kept = mesh.with_alive(tile.alive) if mesh is not None else np.compress(tile.alive, tile.source, axis=0)
    return kept, replace(trim_report, triangles_after=int(np.count_nonzero(tile.alive)), removed=removed,
                         unreferenced_points=int(xy.shape[0] - used))
