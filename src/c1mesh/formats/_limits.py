"""The memory budget of reading: how many bytes a reader may read and decode.

A header can claim any size; a stream (/dev/zero, a pipe) can be endless. Every reader
therefore checks what it is about to read or allocate against one budget, set by
`read_cloud` for the duration of a read (`memory=` / the CLI's `--memory`). The default
is half the machine's RAM, at most 8 GiB. A reader that would exceed it raises
FormatError naming the file and the field, before allocating.
"""
from __future__ import annotations

import contextlib
import contextvars
import os
import re
from typing import IO, Iterator

from c1mesh.errors import FormatError, InputError

_GIB = 1 << 30
_BUDGET: contextvars.ContextVar[int | None] = contextvars.ContextVar("c1mesh_read_budget", default=None)
_UNITS = {"": 1, "b": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}


def default_memory() -> int:
    """Half the physical RAM, capped at 8 GiB (8 GiB when RAM cannot be asked)."""
    try:
        ram = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, OSError, ValueError):
        return 8 * _GIB
    return int(min(8 * _GIB, max(ram // 2, 256 << 20)))


def parse_memory(text: str | int) -> int:
    """Bytes from '512M', '8G', '2.5GiB' or a plain number of bytes; InputError otherwise."""
    if isinstance(text, int):
        value = text
    else:
        match = re.fullmatch(r"\s*([0-9]+(?:\.[0-9]*)?)\s*([kmgtKMGT]?)(?:i?[bB])?\s*", str(text))
        if match is None:
            raise InputError(f"--memory must be a size such as 512M or 8G, got {text!r}")
        value = int(float(match.group(1)) * _UNITS[match.group(2).lower()])
    if value < 1 << 20:
        raise InputError(f"--memory must be at least 1M, got {text!r}")
    return value


def budget() -> int:
    """Bytes a read may use now (the active `reading_budget`, else the default)."""
    value = _BUDGET.get()
    return default_memory() if value is None else value


@contextlib.contextmanager
def reading_budget(memory: int | str | None) -> Iterator[int]:
    """Make `memory` (bytes, a size string, or None for the default) the budget inside."""
    value = default_memory() if memory is None else parse_memory(memory)
    token = _BUDGET.set(value)
    try:
        yield value
    finally:
        _BUDGET.reset(token)


def _size(n: int) -> str:
    for unit, scale in (("GiB", _GIB), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} bytes"


def check_alloc(nbytes: int, name: str, what: str) -> None:
    """FormatError when decoding `what` of file `name` needs more than the budget."""
    limit = budget()
    if nbytes > limit:
        raise FormatError(f"'{name}': {what} needs {_size(nbytes)}, more than the reading budget of "
                          f"{_size(limit)} (raise it with --memory if the file is genuine).")


def read_bounded(stream: IO[bytes], name: str, limit: int | None = None) -> bytes:
    """All bytes of a stream or non-regular file, FormatError past `limit` (the budget).

    Read in 16 MiB pieces, so an endless source (/dev/zero) stops at the limit instead of
    exhausting memory.
    """
    limit = budget() if limit is None else limit
    pieces, total = [], 0
    while True:
        piece = stream.read(min(16 << 20, limit + 1 - total))
        if isinstance(piece, str):
            raise InputError(f"Input stream '{name}' is in text mode; pass a binary stream such as sys.stdin.buffer.")
        if not piece:
            return b"".join(pieces)
        pieces.append(piece)
        total += len(piece)
        if total > limit:
            raise FormatError(f"Input '{name}' goes on past the reading budget of {_size(limit)}; it is "
                              "endless or larger than --memory allows.")
