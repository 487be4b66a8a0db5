"""Atomic writing of output files, kept under its old name for the format writers.

The rules and the code are in c1mesh.outputs (plain files atomically with their mode
kept, devices and FIFOs straight, everything else refused).
"""
from __future__ import annotations

from c1mesh.outputs import WRITE_BEHIND, atomic_output  # noqa: F401

__all__ = ["atomic_output", "WRITE_BEHIND"]
