"""The examples clean up after themselves."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_fit_scan_example_leaves_no_temporary_folder(tmp_path):
    """Without an output argument fit_scan.py writes into a temporary folder (under TMPDIR)
    and removes it: TMPDIR is empty afterwards."""
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / "fit_scan.py")], capture_output=True,
                          timeout=300, env={**os.environ, "TMPDIR": str(scratch)})
    assert proc.returncode == 0, proc.stderr.decode()
    assert b"wrote " in proc.stdout
    assert list(scratch.iterdir()) == []
