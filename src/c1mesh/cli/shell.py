"""The shell contract of the `c1mesh` command (cli/README.md): exit codes, the one-line
error and usage-error messages, and the signal handling that removes temporary outputs and
exits 128+N. `Group` is the click group class that applies them to every command.
"""
from __future__ import annotations

import os
import signal
import sys
import traceback
import warnings

import click

from c1mesh.core.errors import C1MeshError
from c1mesh.core.outputs import STDIO, remove_live_temps

EXIT_OK, EXIT_FAILURE, EXIT_USAGE, EXIT_PARTIAL = 0, 1, 2, 3


_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


def fail(message: str, debug: bool = False) -> None:
    """One line on stderr (plus the traceback under --debug), then exit 1."""
    if debug:
        traceback.print_exc()
    click.echo(f"c1mesh: error: {message}", err=True)
    sys.exit(EXIT_FAILURE)


def naming(src: str, text: str) -> str:
    """`text` led by the input it is about, unless it names it already (readers do; the
    fit's own errors, such as "not a height field", do not)."""
    name = "<stdin>" if src == STDIO else str(src)
    return text if name in text else f"{name}: {text}"


def message(exc: BaseException) -> str:
    """A one-line description of an exception for the user."""
    if isinstance(exc, C1MeshError):
        text = str(exc)
    elif isinstance(exc, MemoryError):
        text = "out of memory; try a lower --level or split the input"
    elif isinstance(exc, OSError):
        where = f"'{exc.filename}': " if exc.filename else ""
        text = f"{where}{exc.strerror or exc or type(exc).__name__}"
    else:
        text = f"unexpected {type(exc).__name__}: {exc}"
    return " ".join(text.split())


def stderr_is_terminal() -> bool:
    """Whether stderr is a terminal, the one place progress bars are drawn."""
    try:
        return os.isatty(sys.stderr.fileno())
    except (AttributeError, OSError, ValueError):
        return False


def usage_line(exc: click.UsageError) -> str:
    """A usage error as the one line cli/README.md promises: `c1mesh: error: ...`, with
    the command whose --help lists the options."""
    text = " ".join(exc.format_message().split()).rstrip(".")
    where = exc.ctx.command_path if exc.ctx is not None else "c1mesh"
    return f"c1mesh: error: {text}; see '{where} --help'"


class Group(click.Group):
    """A click group whose usage errors are one line on stderr and exit 2, and whose
    unexpected failures are one line and exit 1."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        """click's main, except that a usage error prints one line instead of click's
        Usage/Try/Error block (a caller passing standalone_mode=False gets click's exceptions)."""
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        try:
            code = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except click.exceptions.NoArgsIsHelpError as exc:    # bare `c1mesh`: the help, as click shows it
            exc.show()
            sys.exit(exc.exit_code)
        except click.UsageError as exc:
            click.echo(usage_line(exc), err=True)
            sys.exit(EXIT_USAGE)
        except click.ClickException as exc:
            click.echo(f"c1mesh: error: {' '.join(exc.format_message().split())}", err=True)
            sys.exit(exc.exit_code)
        except click.exceptions.Abort:
            click.echo("c1mesh: error: aborted", err=True)
            sys.exit(EXIT_FAILURE)
        sys.exit(code if isinstance(code, int) else EXIT_OK)

    def invoke(self, ctx):
        previous = {sig: signal.signal(sig, _interrupted) for sig in _SIGNALS}
        try:
            with warnings.catch_warnings():
                # numpy's overflow / invalid-value RuntimeWarnings are not news to a user:
                # a failing run prints its one error line and nothing else.
                warnings.simplefilter("ignore", RuntimeWarning)
                return super().invoke(ctx)
        except (click.exceptions.ClickException, click.exceptions.Exit, click.exceptions.Abort):
            raise
        except Exception as exc:  # noqa: BLE001 — the safety net under every command
            fail(message(exc), debug="--debug" in sys.argv)
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)


def _interrupted(signum, frame) -> None:
    """SIGINT/SIGTERM/SIGHUP: stop the batch's worker processes, remove this process's
    temporary output files, print one line and exit 128+signum at once (no traceback, no
    waiting for threads that may be deep in a write)."""
    if hasattr(signal, "SIGPIPE"):   # the pool's feeder thread writes to the workers' closing pipes
        signal.signal(signal.SIGPIPE, signal.SIG_IGN)
    multiprocessing = sys.modules.get("multiprocessing")
    if multiprocessing is not None:
        children = multiprocessing.active_children()
        for child in children:
            child.terminate()
        for child in children:
            child.join(10)
    remove_live_temps()
    try:
        os.write(2, f"c1mesh: error: interrupted ({signal.Signals(signum).name})\n".encode())
    except OSError:
        pass
    os._exit(128 + signum)


def _worker_interrupted(signum, frame) -> None:
    """A batch worker's signal handler: remove its temporary files and end quietly (the
    parent prints the one line)."""
    remove_live_temps()
    os._exit(128 + signum)


def worker_start() -> None:
    """Initializer of a batch worker process: its own signal handlers (no output line),
    numpy's RuntimeWarnings silenced as in the parent."""
    for sig in _SIGNALS:
        signal.signal(sig, _worker_interrupted)
    warnings.simplefilter("ignore", RuntimeWarning)
