"""The console script c1mesh-python (which bin/c1mesh runs): c1mesh.cli.run, after a
signal handler that turns a Ctrl-C during the command's own imports into its one line.

Importing the command (click, then c1mesh.cli's modules) takes about 0.2 s, before the
command's handler (c1mesh.cli.shell) is installed; a Ctrl-C then printed Python's
KeyboardInterrupt traceback. This module imports nothing but the standard library, so
the window left is the interpreter's own start. It lives outside c1mesh.cli because
importing any module of that package imports click first.
"""
from __future__ import annotations

import os
import signal

SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))
"""The signals the command answers with one line (as c1mesh.cli.shell does)."""


def _interrupted_early(signum, frame) -> None:
    """Before the command's handler: nothing is written yet, so one line and exit 128+signum."""
    try:
        os.write(2, f"c1mesh: error: interrupted ({signal.Signals(signum).name})\n".encode())
    except OSError:
        pass
    os._exit(128 + signum)


def install_early_handler() -> None:
    """Answer SIGINT, SIGTERM and SIGHUP with one line until the command installs its own
    (which removes temporary files and stops workers, and restores this one after)."""
    for sig in SIGNALS:
        signal.signal(sig, _interrupted_early)


def run() -> None:
    """The c1mesh-python console script: the early handler, then c1mesh.cli.run."""
    install_early_handler()
    from c1mesh.cli import run as cli_run     # click and the command: ~0.2 s, now interruptible

    cli_run()
