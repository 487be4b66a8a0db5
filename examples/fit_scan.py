"""The whole pipeline from Python: a scan file in, a smooth mesh and a report out.

Run: python examples/fit_scan.py [input] [output]
Defaults to the bundled analytic sample data_samples/hill.ply; without an output it writes
<input stem>.c1.ply into a temporary folder that it removes when done. Prints the report's
main numbers. A LAS/LAZ input is fitted to
its ground points (classification 2), as airborne LiDAR holds trees and roofs too, e.g.
python examples/fit_scan.py data_samples/4_6_crop.las
"""
import sys
import tempfile
from pathlib import Path

from c1mesh.pipeline.driver import FitOptions
from c1mesh.pipeline.run import fit

here = Path(__file__).resolve().parent.parent
source = Path(sys.argv[1] if len(sys.argv) > 1 else here / "data_samples" / "hill.ply")
ground = (2,) if source.suffix.lower() in (".las", ".laz") else None

with tempfile.TemporaryDirectory() as scratch:
    target = sys.argv[2] if len(sys.argv) > 2 else Path(scratch) / (source.stem + ".c1.ply")
    report = fit(source, target, FitOptions(level=4, classes=ground)).report
print(f"wrote {target}: {report['output_mesh']['vertices']} vertices, {report['output_mesh']['faces']} faces")
print(f"kept {report['points']['kept']} of {report['points']['read']} points; "
      f"triangles {report['triangles']['before_trim']} -> {report['triangles']['after_trim']} after trimming")
print(f"C1 certificate: value jump {report['c1_certificate']['value_jump']:.1e}, "
      f"gradient jump {report['c1_certificate']['gradient_jump']:.1e}")
