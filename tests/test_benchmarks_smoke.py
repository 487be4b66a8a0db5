"""Smoke test of the benchmark suite: `python -m benchmarks --quick` runs and writes a report.

Checks structure only (every section present and not failed, the single-thread and
all-cores engine ratios, memory per input point at levels 2, 4 and 8, the terrain fitted
from training points only); it never asserts speed. --quick runs every section at tiny
sizes: ~25 s of CPU (about that on two idle cores), so it is marked slow.
"""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
HEADINGS = ("## Summary", "## Engine: refine vs matplotlib rHCT vs floor",
            "## Pipeline: c1mesh fit vs Open3D Poisson",
            "## Triangulation: scipy Delaunay vs c1mesh.engine.triangulation.delaunay",
            "## Accuracy: convergence orders and a real terrain",
            "## Noisy data: real scans, overshoot, folded faces, held-out RMS",
            "## Memory: peak RSS of a fit",
            "## Tiles: seamless survey vs one whole fit",
            "## Geo: slope honesty, DEM speed, GLB precision",
            "## Depth frames: pixel grid in the perspective frame vs Delaunay in the axis frame",
            "## Held-out accuracy on noisy ground")


@pytest.mark.slow
def test_quick_benchmark_writes_results(tmp_path):
    done = subprocess.run([sys.executable, "-m", "benchmarks", "--quick", "--out", str(tmp_path)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    results = tmp_path / "RESULTS.md"
    assert results.exists(), done.stderr[-2000:]
    text = results.read_text()
    for heading in HEADINGS:
        assert heading in text, f"missing {heading!r}; stderr:\n{done.stderr[-2000:]}"
    assert "FAILED" not in text and done.returncode == 0, done.stderr[-2000:]
    assert "python -m benchmarks --quick" in text
    assert re.search(r"\| \d+(\.\d+)?× \|", text), "no numeric ratio in RESULTS.md"
    assert "both 1 thread |" in text and re.search(r"c1mesh \d+ threads, matplotlib 1 \|", text)
    for level in (2, 4, 8):
        assert re.search(rf"^\| {level} \| [\d,]+ \| [\d.]+ [MG]iB \|", text, re.M), level
    assert "Fitting sees the training points only" in text
    assert (tmp_path / "engine.png").exists() and (tmp_path / "accuracy.png").exists()
    assert (tmp_path / "tiles.png").exists()


def test_quick_run_without_out_never_writes_into_benchmarks(tmp_path, monkeypatch):
    """--quick without --out writes into a new temporary folder, so the committed
    benchmarks/RESULTS.md and plots survive a smoke run; a full run still defaults to benchmarks/."""
    sys.path.insert(0, str(ROOT))
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", None)
    from benchmarks.__main__ import _output_folder

    quick = _output_folder(None, quick=True)
    assert quick.parent == tmp_path and quick.is_dir() and not any(quick.iterdir())
    assert _output_folder(None, quick=False) == ROOT / "benchmarks"
    assert _output_folder(tmp_path / "mine", quick=True) == tmp_path / "mine"
