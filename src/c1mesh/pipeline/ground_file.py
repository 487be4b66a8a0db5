"""`c1mesh ground`: a LAS/LAZ file rewritten with the ground filter's classes.

Every point record is kept with all its dimensions; only the classification changes: 2
(ground) where c1mesh.stages.ground's filter finds ground, 1 (unclassified) elsewhere.
A user can check the filter's result in any LiDAR viewer, or reuse it in PDAL or lidR;
`c1mesh fit` runs the same filter on a file without class 2.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from c1mesh.core.crs import las_crs
from c1mesh.formats.las import read_las_records, write_las_records
from c1mesh.stages.ground import filter_file_points

GROUND, OTHER = 2, 1
"""The ASPRS classes written: ground, and unclassified for everything else."""


def classify_file(source, handle, output_name: str) -> dict:
    """Read the LAS/LAZ file `source`, classify its points and write them to the binary
    file `handle` (LAZ when output_name ends in .laz). Returns the report: input,
    output, points, ground, the filter's facts and seconds."""
    start = time.perf_counter()
    records = read_las_records(source)
    points = np.column_stack([np.asarray(records.x), np.asarray(records.y), np.asarray(records.z)])
    read = time.perf_counter()
    ground, facts = filter_file_points(points, las_crs(records.header))
    records.classification = np.where(ground, GROUND, OTHER).astype(np.uint8)
    classified = time.perf_counter()
    write_las_records(records, handle, Path(output_name).suffix.lower() == ".laz", output_name)
    return {"input": str(source), "output": output_name, "points": int(len(points)),
            "ground": int(ground.sum()), "classes_written": {"ground": GROUND, "other": OTHER},
            "filter": facts, "seconds": {"read": round(read - start, 3), "classify": round(classified - read, 3),
                                         "write": round(time.perf_counter() - classified, 3)}}
