"""Write a file so that readers only ever see the old file or the complete new one.

Output goes to a temporary file in the target's directory (same file system, so the
final `os.replace` is atomic) and is renamed into place only after the caller's block
finished without an exception. On any failure the temporary file is removed and an
existing target is left untouched.
"""
from __future__ import annotations

import contextlib
import io
import os
import tempfile
from pathlib import Path
from typing import IO, Iterator, Union

from c1mesh.errors import InputError

PathLike = Union[str, "os.PathLike[str]"]


WRITE_BEHIND = 64 << 20
"""Bytes written between two requests to start the kernel's writeback."""


class _WriteBehind(io.FileIO):
    """A file that asks the kernel to start writing its pages out every WRITE_BEHIND bytes.

    The file is fsynced before the rename, so its data must reach the disk anyway; left
    to the end, that fsync of a GB-sized mesh waits ~0.5 s here with nothing else to
    do, while started early the writeback overlaps the computing of later blocks.
    posix_fadvise(DONTNEED) starts the writeback of dirty pages without waiting and
    drops the pages already on disk, so a big output does not crowd the page cache
    either. Where the call is missing or refused, writing goes on as usual.
    """

    _since = 0

    def write(self, data) -> int:
        written = super().write(data)
        self._since += written or 0
        if self._since >= WRITE_BEHIND:
            self._since = 0
            with contextlib.suppress(OSError, AttributeError):
                os.posix_fadvise(self.fileno(), 0, 0, os.POSIX_FADV_DONTNEED)
        return written


def _check_target(path: Path) -> None:
    """Raise InputError when `path` cannot possibly be written (missing dir, is a dir)."""
    parent = path.parent
    if path.is_dir():
        raise InputError(f"Output path '{path}' is a directory; give a file name.")
    if not parent.exists():
        raise InputError(f"Output directory '{parent}' does not exist; create it first.")
    if not parent.is_dir():
        raise InputError(f"Output path '{path}' is inside '{parent}', which is not a directory.")


def _make_temp(path: Path) -> tuple[int, Path]:
    """Create an empty temp file beside `path`; return (fd, temp path) or raise InputError."""
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:
        raise InputError(f"Cannot write '{path}': {exc.strerror or exc}.") from exc
    os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual permissions
    return fd, Path(tmp)


def _umask() -> int:
    """The process's umask, read from /proc where Linux has it: the portable way (set it,
    then restore it) briefly leaves umask 0 for files other threads create meanwhile."""
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    umask = os.umask(0)
    os.umask(umask)
    return umask


@contextlib.contextmanager
def atomic_output(path: PathLike, mode: str = "wb") -> Iterator[IO | Path]:
    """Yield something to write `path` through, and move it into place only on success.

    mode "wb" yields a binary file object, "w" a UTF-8 text file object, "path" the
    temporary file's Path (for libraries that insist on a file name). Raises InputError
    when the directory is missing or not writable.
    """
    if mode not in ("wb", "w", "path"):
        raise ValueError(f"atomic_output mode must be 'wb', 'w' or 'path', not {mode!r}")
    target = Path(path)
    _check_target(target)
    fd, tmp = _make_temp(target)
    try:
        if mode == "path":
            os.close(fd)
            yield tmp
        else:
            opened = (io.BufferedWriter(_WriteBehind(fd, "wb")) if mode == "wb"
                      else os.fdopen(fd, mode, encoding="utf-8"))
            with opened as f:
                yield f
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(exc, OSError):  # disk full, target vanished, ...: a user problem
            raise InputError(f"Cannot write '{target}': {exc.strerror or exc}.") from exc
        raise
