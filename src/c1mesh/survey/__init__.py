"""Layer 4: surveys larger than memory or cut into files: tile grids, halos, spill files, joins, the Dask runner."""
