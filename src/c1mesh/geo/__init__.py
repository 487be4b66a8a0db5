"""Layer 4: the georeferenced side: CRS, GeoTIFF rasters, previews."""
