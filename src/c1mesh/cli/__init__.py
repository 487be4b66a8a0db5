"""The `c1mesh` command: a thin click layer over the library.

Exit codes (cli/README.md): 0 success, 1 failure, 2 usage error, 3 batch where some
inputs failed, 128+N killed by signal N (SIGINT 130, SIGTERM 143, SIGHUP 129). Errors
are one line on stderr; --debug shows the traceback. A usage error is everything the
command line shows on its own (values, conflicting options, output extensions): all of
its problems are named in that one line, before any input is read (`usage_error`). Progress goes to stderr only when
stderr is a terminal. Every output path is checked (c1mesh.core.outputs) before any input is
read. Nothing heavy (numpy, scipy, open3d) is imported until a command runs, so --help
and usage errors are quick.

The modules, from the shell down: `commands` (the click group `main` and its commands),
`fitting` (running fit on one input, a batch or a survey), `usage` (usage errors),
`options` (option values), `outputs_check` (outputs checked before reading), `messages`
and `progress` (what goes to stderr), `shell` (exit codes, one-line errors, signals).
"""
from __future__ import annotations

import contextlib
import io
from typing import Sequence

import click

from c1mesh.cli.commands import fit, info, main, preview, schemes
from c1mesh.cli.shell import EXIT_FAILURE, EXIT_OK, EXIT_PARTIAL, EXIT_USAGE, usage_line
from c1mesh.cli.usage import USAGE_CHECKS, check_usage
from c1mesh.core.platform_memory import hold_freed_heap, prefer_small_pages, sleep_idle_blas


__all__ = ["main", "run", "usage_error", "fit", "info", "preview", "schemes",
           "EXIT_OK", "EXIT_FAILURE", "EXIT_USAGE", "EXIT_PARTIAL"]

def usage_error(argv: Sequence[str]) -> str | None:
    """The one line `c1mesh ARGV...` prints for a usage error (it then exits 2), or None
    when the command line is well formed. Only parses and checks the arguments: reads no
    input, writes nothing (the text of a --help or --version in argv is discarded)."""
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            with main.make_context("c1mesh", list(argv)) as ctx:
                name, command, rest = main.resolve_command(ctx, [*ctx._protected_args, *ctx.args])
                with command.make_context(name, rest, parent=ctx) as sub:
                    if name in USAGE_CHECKS:
                        check_usage(sub)
    except click.exceptions.Exit:
        return None
    except click.exceptions.NoArgsIsHelpError:     # bare `c1mesh` prints the help and exits 2
        return f"c1mesh: error: give a command ({', '.join(main.commands)}); see 'c1mesh --help'"
    except click.UsageError as exc:
        return usage_line(exc)
    return None


def run() -> None:
    """The c1mesh-python console script, which the `c1mesh` launcher (bin/c1mesh) runs: named
    c1mesh in usage lines and shell completion (_C1MESH_COMPLETE) whatever its file name.
    Before numpy is first imported, numpy's huge pages are turned off for the command and
    the processes it starts (core.platform_memory.prefer_small_pages), glibc keeps the
    heap they free for their next arrays (hold_freed_heap), and OpenBLAS's idle threads
    sleep instead of spinning (sleep_idle_blas)."""
    prefer_small_pages()
    hold_freed_heap()
    sleep_idle_blas()
    main(prog_name="c1mesh")
