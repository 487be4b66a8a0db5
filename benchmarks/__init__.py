"""c1mesh benchmarks (issue #4): where c1mesh stands against what users already have.

``python -m benchmarks`` (full, ~15 min on 2 cores) or ``python -m benchmarks --quick``
writes RESULTS.md and PNG plots. Sections, one module each:
  engine         refine vs matplotlib's reduced HCT refine_field, and vs a floor
  pipeline       `c1mesh fit` end to end vs Open3D Poisson reconstruction
  triangulation  scipy Delaunay vs c1mesh.engine.triangulation.delaunay
  accuracy       convergence orders (sextic, quintic, rHCT, Clough-Tocher) and a real DEM
  memory         peak RSS of a fit vs the size of its output
  geo            slope from the spline vs Horn / gdaldem, DEM time vs a level-2 fit, GLB vs PLY
Every speed figure is a ratio to a peer measured in the same run (median of repetitions).
"""
