"""Layer 2: the RSD spline itself: shape-function schemes, the interpolator, refinement, mesh topology, point location and Delaunay triangulation."""
