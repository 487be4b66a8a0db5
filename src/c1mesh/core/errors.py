"""Exceptions that c1mesh raises for problems a user can fix.

The library raises these and never prints or exits; the CLI turns them into one line on
stderr and an exit code. Every message is one sentence that says what is wrong and, where
possible, what to try.
"""
from __future__ import annotations


class C1MeshError(Exception):
    """Base class of every error c1mesh reports to a user (exit code 1 in the CLI)."""


class InputError(C1MeshError, ValueError):
    """An input file or array cannot be used: unreadable, malformed, empty, wrong shape."""


class FormatError(InputError):
    """A file is not valid in the format it claims (bad header, truncated body, garbage)."""


class NotAHeightFieldError(C1MeshError):
    """The points are not a graph z = f(x, y) over the chosen plane."""


class DependencyError(C1MeshError, ImportError):
    """An optional dependency (or the system library it needs) is missing."""
