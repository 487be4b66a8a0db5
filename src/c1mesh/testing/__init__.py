"""Analytic samples with exact normals and surface quality measures, for the tests, examples and benchmarks (documented, not part of the fit)."""
