"""What c1mesh prints on stderr, for the tests that read it: on a terminal (a
pseudo-terminal, where progress and the advice to smooth are drawn), and the advice's line."""
from __future__ import annotations

import os
import pty
import re
import select
import subprocess
import sys
import time

from c1mesh.stages.warnings import smoothing_suggestion

ADVICE = re.compile(r"c1mesh: note: .+?: " + re.escape(smoothing_suggestion(1, 1)).replace("100%", r"\d+%"))
"""The note advising --smooth auto for noisy heights (c1mesh.stages.warnings), any share,
after the input's name (a path, which may hold ':')."""


def stderr_on_a_terminal(args: list[str], timeout: float = 300) -> str:
    """What `c1mesh ARGS` writes to stderr when stderr is a terminal (a pseudo-terminal
    here), read as it runs; fails on a non-zero exit or after timeout seconds."""
    leader, follower = pty.openpty()
    child = subprocess.Popen([sys.executable, "-m", "c1mesh.cli", *args], stdin=subprocess.DEVNULL,
                             stdout=subprocess.DEVNULL, stderr=follower)
    os.close(follower)
    chunks, deadline = [], time.monotonic() + timeout
    try:
        while select.select([leader], [], [], max(0.0, deadline - time.monotonic()))[0]:
            try:
                chunk = os.read(leader, 4096)
            except OSError:                 # EIO: the child closed its end
                break
            if not chunk:
                break
            chunks.append(chunk)
    finally:
        os.close(leader)
    shown = b"".join(chunks).decode(errors="replace")
    if child.poll() is None and time.monotonic() >= deadline:
        child.kill()
    assert child.wait(timeout=10) == 0, shown
    return shown
