"""The memory budget of reading: how many bytes a reader may read and decode.

A header can claim any size; a stream (/dev/zero, a pipe) can be endless. Every reader
therefore checks what it is about to read or allocate against one budget, set by
`read_cloud` for the duration of a read (`memory=` / the CLI's `--memory`). The default
is half the machine's RAM, at most 8 GiB. A reader that would exceed it raises
FormatError naming the file and the field, before allocating.

Two limits hold only while the user has not given --memory, because they refuse inputs
that are possible but almost certainly hostile; an explicit --memory lifts them up to
the budget:
  - a non-regular input (a device, FIFO, or stdin from a pipe) may deliver at most STREAM_LIMIT
    bytes, so /dev/zero or an endless pipe stops early, not at the budget;
  - a compressed body may decode to at most max(SANE_RATIO x its compressed size,
    SMALL_DECODE) bytes (`check_expansion`), so a small LZF bomb is refused before
    it is decoded.
"""
from __future__ import annotations

import contextlib
import contextvars
import os
import re
from typing import IO, Callable, Iterator

from c1mesh.core.errors import FormatError, InputError

_GIB = 1 << 30
_BUDGET: contextvars.ContextVar[int | None] = contextvars.ContextVar("c1mesh_read_budget", default=None)
_EXPLICIT: contextvars.ContextVar[bool] = contextvars.ContextVar("c1mesh_read_budget_given", default=False)
#: Most bytes a device, FIFO or piped stdin may deliver unless --memory is given.
STREAM_LIMIT = 256 << 20
#: Most decoded bytes per compressed byte unless --memory is given. LZF can expand 88-fold
#: (a run of zeros); point data compresses far less (the mug sample 2.9-fold, an organised
#: frame that is 95 % NaN about 16-fold).
SANE_RATIO = 24
#: Decoded sizes up to this are allowed whatever the ratio: small files cannot hurt.
SMALL_DECODE = 16 << 20
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
    token, given = _BUDGET.set(value), _EXPLICIT.set(memory is not None)
    try:
        yield value
    finally:
        _BUDGET.reset(token)
        _EXPLICIT.reset(given)


def budget_given() -> bool:
    """True when the active budget is the user's --memory rather than the default."""
    return _EXPLICIT.get()


def stream_limit() -> int:
    """Most bytes a non-regular input may deliver: the budget, at most STREAM_LIMIT
    unless --memory was given."""
    return budget() if budget_given() else min(budget(), STREAM_LIMIT)


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


def check_expansion(packed: int, unpacked: int, name: str, what: str) -> None:
    """FormatError when `packed` compressed bytes claim to decode to a suspicious `unpacked`.

    Unless --memory is given, at most max(SANE_RATIO x packed, SMALL_DECODE) bytes; with
    it, whatever the budget allows (checked by the caller with check_alloc).
    """
    if budget_given() or unpacked <= max(SANE_RATIO * packed, SMALL_DECODE):
        return
    raise FormatError(f"'{name}': {what} would decode {_size(packed)} to {_size(unpacked)} "
                      f"({unpacked / max(packed, 1):.0f}-fold; point data compresses less than "
                      f"{SANE_RATIO}-fold), a decompression bomb; give --memory to decode it anyway.")


def read_bounded(stream: IO[bytes], name: str, limit: int | None = None,
                 head_check: Callable[[bytes], None] | None = None) -> bytes:
    """All bytes of a stream or non-regular file, FormatError past `limit` (`stream_limit()`).

    Read in 16 MiB pieces, so an endless source (/dev/zero) stops at the limit instead of
    exhausting memory. `head_check(first_bytes)`, if given, runs on the first piece (up to
    64 KiB) before more is read, so that a stream of garbage fails at once.
    """
    limit = stream_limit() if limit is None else limit
    first = stream.read(min(HEAD_BYTES, limit + 1))
    if isinstance(first, str):
        raise InputError(f"Input stream '{name}' is in text mode; pass a binary stream such as sys.stdin.buffer.")
    if head_check is not None and first:
        head_check(first)
    pieces, total = [first], len(first)
    if not first:
        return b""
    while True:
        piece = stream.read(min(16 << 20, limit + 1 - total))
        if isinstance(piece, str):
            raise InputError(f"Input stream '{name}' is in text mode; pass a binary stream such as sys.stdin.buffer.")
        if not piece:
            return b"".join(pieces)
        pieces.append(piece)
        total += len(piece)
        if total > limit:
            raise _endless(name, limit)


def _endless(name: str, limit: int) -> FormatError:
    """The error for a stream that delivers more than `limit` bytes."""
    if not budget_given() and limit == STREAM_LIMIT:
        return FormatError(f"Input '{name}' is not a regular file and goes on past {_size(limit)}; it is "
                           "endless, or give --memory to read more from it.")
    return FormatError(f"Input '{name}' goes on past the reading budget of {_size(limit)}; it is "
                       "endless or larger than --memory allows.")


#: Bytes of a stream looked at before the rest is read (`read_bounded`'s head_check).
HEAD_BYTES = 64 << 10
