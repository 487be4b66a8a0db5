"""Output paths: check them all before any input is read, then write them so that no input
and no complete file is ever destroyed.

The rules (cli/README.md, "Output paths"):

* Every output (mesh, report, and whatever else a command writes: pass it as one more
  named output) is resolved, symlinks followed, and compared with every input and every
  other output by real path and by (st_dev, st_ino), before any work starts. A clash is
  refused with OutputError.
* A regular file or a new path is written atomically: a temporary file beside the real
  target (same file system), fsync, then `os.replace`. An existing file keeps its
  permission bits (0600 stays 0600) and, where the process may set it, its owner. A
  symlink stays a symlink; the file it points to is replaced.
* A character device or FIFO (/dev/null, /dev/full, a named pipe), or a path that goes
  through a file descriptor (/dev/stdout, /dev/fd/N, /proc/self/fd/N), is written
  straight: no temporary file, no rename.
* Anything else (a directory, a block device, a socket) is refused.

`Outputs` writes a set of planned targets as one transaction: each `open` writes to a
temporary file, and `commit` renames them all into place only after every one of them was
written, so a failed report never leaves a mesh behind. The temporary files alive at any
moment are listed, so a signal handler can remove them (`remove_live_temps`).

This module imports nothing heavy (no numpy): the CLI checks its outputs with it before
loading the numerical stack.
"""
from __future__ import annotations

import contextlib
import io
import os
import signal
import stat
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Iterable, Iterator, Sequence, Union

from c1mesh.core.errors import InputError

PathLike = Union[str, "os.PathLike[str]"]

STDIO = "-"
"""The output name that means the process's own stream (stdout for a mesh)."""

MESH_FORMATS = ("ply", "obj", "stl", "off", "glb")
"""Mesh file extensions c1mesh writes (the writers are in c1mesh.formats)."""

RASTER_FORMATS = ("tif", "tiff")
"""GeoTIFF DEM extensions c1mesh writes (c1mesh.geo.raster; a fit needs --resolution for them)."""

CONTOUR_FORMATS = ("gpkg", "geojson", "shp")
"""Contour line extensions c1mesh writes (--contours; c1mesh.geo.contour_file)."""


def contour_path_problem(path: str) -> str | None:
    """Why `path` names no contour format c1mesh writes, or None (plain Python: the CLI's
    usage check and the library's both say it this way)."""
    if Path(path).suffix.lower().lstrip(".") in CONTOUR_FORMATS:
        return None
    names = [f".{fmt}" for fmt in CONTOUR_FORMATS]
    return f"the contours '{path}' must be a {', '.join(names[:-1])} or {names[-1]} file"

OUTPUT_FORMATS = MESH_FORMATS + RASTER_FORMATS
"""Every output extension of `c1mesh fit`: the one list behind its help, errors and docs."""

TEXT_FORMATS = ("obj", "off")
"""Output formats written as text whatever the options (c1mesh.formats' writers); PLY is
text with --ascii (ASCII_CHOICE), every other output binary."""
ASCII_CHOICE = ("ply",)
"""Output formats that --ascii turns from binary into text."""


def is_binary_output(fmt: str, ascii: bool = False) -> bool:
    """Whether output format `fmt` ('ply', 'tif', ...) is written as bytes a terminal cannot
    show, so that `fit -o -` refuses to send it to one (cli/README.md, Output paths)."""
    return fmt not in TEXT_FORMATS and not (ascii and fmt in ASCII_CHOICE)

INPUT_FORMATS = ("ply", "obj", "xyz", "txt", "csv", "pcd", "las", "laz", "copc", "png", "tif", "tiff")
"""Input format names (--input-format, and file extensions; COPC files end in .laz): the
readers registered in c1mesh.formats, which checks that it reads exactly these."""
LAS_FORMATS = ("las", "laz", "copc")
"""The LAS family among INPUT_FORMATS: classification codes, heights along world z."""
DEM_AXES = ("auto", "z", "+z")
"""--axis values a GeoTIFF output allows: a DEM is heights along world z over x, y."""

WRITE_BEHIND = 64 << 20
"""Bytes written between two requests to start the kernel's writeback."""

_FD_PREFIXES = ("/proc/", "/dev/fd/")
_TEMP_STEM = 64
"""Characters of the target's name kept in its temporary file's name (names stay < 255 bytes)."""

_LIVE_TEMPS: set[str] = set()


class OutputError(InputError):
    """An output path cannot be written, or writing it would destroy an input or another output."""


@dataclass(frozen=True)
class Target:
    """One planned output.

    label: what it is, for messages ("output", "report"); path: as given; kind: "stdio"
    (the process's stream, path "-"), "straight" (device, FIFO or file descriptor: written
    in place) or "atomic" (regular file or new path: temp + rename); real: the resolved
    path that is written (atomic) or opened (straight); identity: (st_dev, st_ino) of an
    existing regular file there; mode/owner: its permission bits and (uid, gid).
    """

    label: str
    path: str
    kind: str
    real: str | None = None
    identity: tuple[int, int] | None = None
    mode: int | None = None
    owner: tuple[int, int] | None = None


# ------------------------------------------------------------------------------ planning
def format_key(fmt: str | None, where: str, supported: Sequence[str], direction: str,
               error: type[InputError] = InputError) -> str:
    """Normalise a format name or extension ('.PLY' -> 'ply') and check it is in `supported`.

    where: the file named in the message; direction: "input" or "output". Raises `error`.
    """
    key = (fmt or "").lower().lstrip(".")
    if not key:
        raise error(f"Cannot tell the {direction} format of '{where}' from its name; "
                    f"use one of the extensions {', '.join(supported)}.")
    if key not in supported:
        raise error(f"Unsupported {direction} format '{key}' for '{where}'; supported: {', '.join(supported)}.")
    return key


def mesh_format(path: PathLike, fmt: str | None = None, target: Target | None = None) -> str:
    """The mesh format of `path` ('.PLY' -> 'ply') from `fmt` or its extension; OutputError if
    unknown. A stream, device or FIFO target without an extension (/dev/stdout) gets PLY."""
    key = fmt or Path(path).suffix
    if not key.lstrip(".") and target is not None and target.kind != "atomic":
        return "ply"
    return format_key(key, str(path), MESH_FORMATS, "output", OutputError)


def plan_outputs(outputs: Iterable[tuple[str, PathLike | None]],
                 inputs: Sequence[object] = ()) -> list[Target]:
    """Check every (label, path) output against the file system, the inputs and each other.

    `inputs` are paths, "-" (stdin) or binary streams; a stream or "-" is compared by the
    identity of its file descriptor. Outputs that are None are skipped. Returns the targets
    in order, or raises OutputError naming the output and what is wrong. Nothing is read
    and nothing but a probe file (created and removed at once) is written.
    """
    sources = [_source_identity(src) for src in inputs]
    targets = [_plan_one(label, os.fspath(path)) for label, path in outputs if path is not None]
    for target in targets:
        for name, real, identity in sources:
            if _same(target, real, identity):
                raise OutputError(f"The {target.label} '{target.path}' is the input '{name}'; "
                                  "refusing to overwrite an input.")
    for i, first in enumerate(targets):
        for second in targets[i + 1:]:
            if first.kind != "stdio" and _same(second, first.real if first.kind == "atomic" else None,
                                               first.identity):
                raise OutputError(f"The {first.label} '{first.path}' and the {second.label} "
                                  f"'{second.path}' are the same file; give them different names.")
    return targets


def _same(target: Target, real: str | None, identity: tuple[int, int] | None) -> bool:
    """True when `target` writes the file known by real path `real` or by `identity`."""
    if identity is not None and target.identity == identity:
        return True
    return target.kind == "atomic" and real is not None and target.real == real


def _source_identity(src: object) -> tuple[str, str | None, tuple[int, int] | None]:
    """(name, real path, (st_dev, st_ino)) of an input; identity only for regular files."""
    if isinstance(src, (str, os.PathLike)) and os.fspath(src) != STDIO:
        path = os.fspath(src)
        real = os.path.realpath(path)
        try:
            info = os.stat(path)
        except (OSError, ValueError):
            return path, real, None
        return path, real, (info.st_dev, info.st_ino) if stat.S_ISREG(info.st_mode) else None
    fileno = getattr(src if src != STDIO else sys.stdin, "fileno", None)
    name = "-" if src == STDIO else str(getattr(src, "name", "<stream>"))
    try:
        info = os.fstat(fileno()) if fileno else None
    except (OSError, ValueError, io.UnsupportedOperation):
        info = None
    if info is None or not stat.S_ISREG(info.st_mode):
        return name, None, None
    return name, None, (info.st_dev, info.st_ino)


def _plan_one(label: str, path: str) -> Target:
    """Classify one output path (see the module docstring); OutputError when it cannot be written."""
    if path == STDIO:
        try:
            info = os.fstat(sys.stdout.fileno())
        except (AttributeError, OSError, ValueError):
            raise OutputError(f"Standard output is closed; the {label} '-' needs it "
                              "(give a file name instead).") from None
        except io.UnsupportedOperation:      # replaced by an in-memory stream (tests)
            return Target(label, path, "stdio")
        regular = stat.S_ISREG(info.st_mode)
        return Target(label, path, "stdio", identity=(info.st_dev, info.st_ino) if regular else None)
    if not path:
        raise OutputError(f"The {label} path is empty; give a file name.")
    try:
        info = os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        return _plan_new(label, path)
    except OSError as exc:
        raise OutputError(f"Cannot write the {label} '{path}': {_reason(exc)}.") from exc
    mode = info.st_mode
    if stat.S_ISDIR(mode):
        raise OutputError(f"The {label} path '{path}' is a directory; give a file name.")
    identity = (info.st_dev, info.st_ino) if stat.S_ISREG(mode) else None
    if _straight(path, mode):
        return Target(label, path, "straight", real=path, identity=identity)
    if not stat.S_ISREG(mode):
        kind = "block device" if stat.S_ISBLK(mode) else "socket" if stat.S_ISSOCK(mode) else "special file"
        raise OutputError(f"The {label} path '{path}' is a {kind}; c1mesh writes only regular files, "
                          "character devices (such as /dev/null) and FIFOs.")
    real = os.path.realpath(path)
    _probe_directory(label, path, os.path.dirname(real))
    return Target(label, path, "atomic", real=real, identity=identity, mode=stat.S_IMODE(mode),
                  owner=(info.st_uid, info.st_gid))


def _straight(path: str, mode: int) -> bool:
    """Whether an existing `path` of st_mode `mode` is written in place: a character device,
    a FIFO, or a file reached through a file descriptor."""
    return stat.S_ISCHR(mode) or stat.S_ISFIFO(mode) or (stat.S_ISREG(mode) and _through_descriptor(path))


def is_file_output(path: str) -> bool:
    """Whether output `path` is or will be a regular file of its own (a new path, or a file
    not reached through a descriptor): the outputs whose format must come from their
    extension. A device, FIFO or /dev/stdout without one gets binary PLY (mesh_format);
    a directory, socket or block device is refused by plan_outputs."""
    try:
        mode = os.stat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        return True
    except (OSError, ValueError):
        return False
    return stat.S_ISREG(mode) and not _straight(path, mode)


def _plan_new(label: str, path: str) -> Target:
    """A path that does not exist yet (or a dangling symlink): its directory must take a file."""
    real = os.path.realpath(path)
    parent = os.path.dirname(real)
    try:
        parent_info = os.stat(parent)
    except FileNotFoundError:
        raise OutputError(f"Output directory '{os.path.dirname(path) or parent}' does not exist; "
                          "create it first.") from None
    except NotADirectoryError:
        parent_info = None
    except OSError as exc:
        raise OutputError(f"Cannot write the {label} '{path}': {_reason(exc)}.") from exc
    if parent_info is None or not stat.S_ISDIR(parent_info.st_mode):
        raise OutputError(f"The {label} '{path}' is inside '{os.path.dirname(path) or parent}', "
                          "which is not a directory.")
    _check_name_length(label, real)
    _probe_directory(label, path, parent)
    return Target(label, path, "atomic", real=real)


def _check_name_length(label: str, real: str) -> None:
    name = os.path.basename(real).encode("utf-8", "surrogateescape")
    try:
        limit = os.pathconf(os.path.dirname(real), "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):
        limit = 255
    if len(name) > limit:
        raise OutputError(f"The {label} file name '{os.path.basename(real)[:40]}...' is {len(name)} bytes "
                          f"long; this file system allows {limit}.")


def _probe_directory(label: str, path: str, directory: str) -> None:
    """Create and remove a temporary file in `directory`: the only proof it takes one
    (permissions, read-only mounts, /proc and the like), cheap, and done before the work."""
    try:
        fd, probe = tempfile.mkstemp(dir=directory, prefix=".c1mesh-probe.", suffix=".tmp")
    except OSError as exc:
        raise OutputError(f"Cannot write the {label} '{path}': {_reason(exc)}.") from exc
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)


def _through_descriptor(path: str) -> bool:
    """True when `path` or a symlink on its way is /dev/fd/N, /dev/stdout, /proc/self/fd/N, ...:
    such a path names an open file of this process, which is written in place."""
    current = os.path.abspath(path)
    for _ in range(40):
        if current.startswith(_FD_PREFIXES):
            return True
        if not os.path.islink(current):
            return False
        current = os.path.normpath(os.path.join(os.path.dirname(current), os.readlink(current)))
    return False


def _reason(exc: OSError) -> str:
    """A short reason for an OSError, without repeating the path."""
    return exc.strerror or str(exc) or type(exc).__name__


# ------------------------------------------------------------------------------- writing
class _Raw(io.FileIO):
    """A file whose write errors (disk full, ...) become OutputError naming the target, and
    that, for big atomic outputs, asks the kernel to start writeback every WRITE_BEHIND bytes.

    The temp file is fsynced before the rename, so its data must reach the disk anyway; left
    to the end, that fsync of a GB-sized mesh waits with nothing else to do, while started
    early the writeback overlaps the computing of later blocks. posix_fadvise(DONTNEED)
    starts the writeback of dirty pages without waiting and drops the pages already on disk.
    """

    target_name = "<output>"
    write_behind = False
    _since = 0

    def write(self, data) -> int:
        try:
            written = super().write(data)
        except OSError as exc:
            raise OutputError(f"Cannot write '{self.target_name}': {_reason(exc)}.") from exc
        if self.write_behind:
            self._since += written or 0
            if self._since >= WRITE_BEHIND:
                self._since = 0
                with contextlib.suppress(OSError, AttributeError):
                    os.posix_fadvise(self.fileno(), 0, 0, os.POSIX_FADV_DONTNEED)
        return written


class _LazyTemp(io.RawIOBase):
    """The temporary file of an atomic target, created at the first write (or seek,
    fileno), not when the output is opened.

    A run opens its outputs before it reads its input; an input that blocks (a FIFO with no
    writer yet) would otherwise keep an empty temp file beside the target, left behind if
    the run is killed with SIGKILL. Writes go to a _Raw (errors name the target, early
    writeback) once the file exists.
    """

    def __init__(self, target: Target):
        super().__init__()
        self.target = target
        self.path: str | None = None
        self._raw: _Raw | None = None

    def create(self) -> str:
        """The temp file's path, creating it now if nothing was written yet."""
        if self._raw is None:
            fd, self.path = _make_temp(self.target)
            self._raw = _Raw(fd, "wb")
            self._raw.target_name, self._raw.write_behind = self.target.path, True
        return self.path

    def remove(self) -> None:
        """Close and delete the temp file, if it was created."""
        if self._raw is not None:
            with contextlib.suppress(OSError, ValueError):
                self._raw.close()
            _remove_temp(self.path)

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def write(self, data) -> int:
        self.create()
        return self._raw.write(data)

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        if self._raw is None and offset == 0 and whence in (io.SEEK_SET, io.SEEK_CUR):
            return 0
        self.create()
        return self._raw.seek(offset, whence)

    def tell(self) -> int:
        return 0 if self._raw is None else self._raw.tell()

    def truncate(self, size: int | None = None) -> int:
        self.create()
        return self._raw.truncate(size)

    def fileno(self) -> int:
        self.create()
        return self._raw.fileno()

    def close(self) -> None:
        if self._raw is not None:
            self._raw.close()
        super().close()


def _wrap(raw: io.RawIOBase, mode: str) -> IO:
    buffered = io.BufferedWriter(raw)
    return buffered if mode == "wb" else io.TextIOWrapper(buffered, encoding="utf-8")


def _finish(handle: IO, name: str, sync: bool) -> None:
    """Flush (and fsync) `handle`; OutputError for a failure (a full disk shows up here)."""
    try:
        handle.flush()
        if sync:
            os.fsync(handle.fileno())
    except OSError as exc:
        raise OutputError(f"Cannot write '{name}': {_reason(exc)}.") from exc


class Outputs:
    """Write planned targets as one transaction.

    `open(target)` yields a file to write through; for an atomic target the data goes to a
    temporary file that is renamed into place by `commit()` (or at once, with
    deferred=False). Leaving the `with Outputs(...)` block with an exception, or `discard()`,
    removes every temporary file that was not committed.
    """

    def __init__(self, deferred: bool = True):
        self.deferred = deferred
        self._pending: list[tuple[str, Target]] = []

    def __enter__(self) -> "Outputs":
        return self

    def __exit__(self, kind, value, tb) -> None:
        if kind is not None:
            self.discard()

    @contextlib.contextmanager
    def open(self, target: Target, mode: str = "wb") -> Iterator[IO | Path]:
        """A file for `target`: mode "wb" binary, "w" UTF-8 text, "path" the temp file's Path
        (atomic targets only, for libraries that insist on a file name)."""
        if mode not in ("wb", "w", "path"):
            raise ValueError(f"output mode must be 'wb', 'w' or 'path', not {mode!r}")
        if target.kind == "stdio":
            stream = sys.stdout.buffer if mode == "wb" else sys.stdout
            yield stream
            _finish(stream, "<stdout>", sync=False)
        elif target.kind == "straight":
            if mode == "path":
                raise OutputError(f"The {target.label} '{target.path}' is not a regular file; "
                                  "this writer needs one.")
            with self._straight(target, mode) as handle:
                yield handle
        else:
            with self._atomic(target, mode) as written:
                yield written

    @contextlib.contextmanager
    def _straight(self, target: Target, mode: str) -> Iterator[IO]:
        try:
            raw = _Raw(target.path, "wb")
        except OSError as exc:
            raise OutputError(f"Cannot write the {target.label} '{target.path}': "
                              f"{_reason(exc)}.") from exc
        raw.target_name = target.path
        handle = _wrap(raw, mode)
        try:
            yield handle
            _finish(handle, target.path, sync=False)
        finally:
            with contextlib.suppress(OSError, ValueError):
                handle.close()

    @contextlib.contextmanager
    def _atomic(self, target: Target, mode: str) -> Iterator[IO | Path]:
        if mode == "path":
            fd, tmp = _make_temp(target)
            os.close(fd)
            temp = None
        else:
            temp, tmp = _LazyTemp(target), None
        try:
            if temp is None:
                yield Path(tmp)
            else:
                with _wrap(temp, mode) as handle:
                    yield handle
                    _finish(handle, target.path, sync=True)
                    tmp = temp.create()          # an output with nothing written still exists
            _settle_permissions(tmp, target)
        except BaseException:
            if temp is not None:
                temp.remove()
            elif tmp is not None:
                _remove_temp(tmp)
            raise
        if self.deferred:
            self._pending.append((tmp, target))
        else:
            self._replace(tmp, target)

    def commit(self) -> None:
        """Rename every written temporary file into place, in the order they were opened."""
        while self._pending:
            tmp, target = self._pending.pop(0)
            self._replace(tmp, target)

    def discard(self) -> None:
        """Remove the temporary files not yet committed."""
        while self._pending:
            _remove_temp(self._pending.pop()[0])

    def _replace(self, tmp: str, target: Target) -> None:
        try:
            os.replace(tmp, target.real)
        except OSError as exc:
            _remove_temp(tmp)
            self.discard()
            raise OutputError(f"Cannot write the {target.label} '{target.path}': "
                              f"{_reason(exc)}.") from exc
        _LIVE_TEMPS.discard(tmp)


def _make_temp(target: Target) -> tuple[int, str]:
    """Create an empty temp file beside the real target and list it as live; (fd, path)."""
    directory, name = os.path.split(target.real)
    blocked = hasattr(signal, "pthread_sigmask")
    signals = {s for s in (getattr(signal, n, None) for n in ("SIGINT", "SIGTERM", "SIGHUP")) if s}
    if blocked:   # a signal between mkstemp and the listing would leave the file behind
        previous = signal.pthread_sigmask(signal.SIG_BLOCK, signals)
    try:
        fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{name[:_TEMP_STEM]}.", suffix=".tmp")
        _LIVE_TEMPS.add(tmp)
    except OSError as exc:
        raise OutputError(f"Cannot write '{target.path}': {_reason(exc)}.") from exc
    finally:
        if blocked:
            signal.pthread_sigmask(signal.SIG_SETMASK, previous)
    return fd, tmp


def _settle_permissions(tmp: str, target: Target) -> None:
    """Give the temp file the mode (and owner) of the file it replaces, or 0666 minus the
    umask for a new file (mkstemp makes 0600)."""
    os.chmod(tmp, target.mode if target.mode is not None else 0o666 & ~_umask())
    if target.owner is not None and hasattr(os, "chown"):
        with contextlib.suppress(OSError):
            if (os.stat(tmp).st_uid, os.stat(tmp).st_gid) != target.owner:
                os.chown(tmp, *target.owner)
                os.chmod(tmp, target.mode)   # chown clears set-id bits


def _remove_temp(tmp: str) -> None:
    with contextlib.suppress(OSError):
        os.unlink(tmp)
    _LIVE_TEMPS.discard(tmp)


def register_temp(path: PathLike) -> None:
    """List `path` as a temporary file of this process, removed by `remove_live_temps` (the
    CLI's SIGINT/SIGTERM/SIGHUP handler) if the process is interrupted. Register a path
    before creating the file: a signal between the two then finds nothing to remove, never
    an unlisted file."""
    _LIVE_TEMPS.add(os.fspath(path))


def unregister_temp(path: PathLike) -> None:
    """Stop listing `path` (it was renamed into place or removed)."""
    _LIVE_TEMPS.discard(os.fspath(path))


def remove_live_temps() -> None:
    """Remove every temporary output file of this process (for signal handlers)."""
    for tmp in list(_LIVE_TEMPS):
        _remove_temp(tmp)


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
    """Write one output path by the rules above, committed when the block ends without error.

    mode "wb" yields a binary file object, "w" a UTF-8 text file object, "path" the
    temporary file's Path (Outputs.open: ValueError for any other). Raises OutputError
    (an InputError) when the path cannot be written.
    """
    (target,) = plan_outputs([("output", path)])
    if target.kind == "stdio":
        target = Target("output", os.path.abspath(path), "atomic", real=os.path.realpath(path))
    with Outputs(deferred=False).open(target, mode) as handle:
        yield handle
