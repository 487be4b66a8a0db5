"""Small helpers shared by the readers: colour conversion and field-name conventions."""
from __future__ import annotations

import warnings

import numpy as np

from c1mesh.core.errors import FormatError

#: Names under which files store normal components, lower-case, per axis.
NORMAL_NAMES = (
    ("nx", "normal_x", "normalx", "n_x"),
    ("ny", "normal_y", "normaly", "n_y"),
    ("nz", "normal_z", "normalz", "n_z"),
)
#: Names under which files store colour channels, lower-case, per channel (r, g, b, a).
COLOR_NAMES = (
    ("red", "r", "diffuse_red"),
    ("green", "g", "diffuse_green"),
    ("blue", "b", "diffuse_blue"),
    ("alpha", "a", "diffuse_alpha"),
)


def find_columns(names: list[str], candidates: tuple[tuple[str, ...], ...]) -> list[int | None]:
    """Index in `names` (case-insensitive) of the first matching alias per axis, or None."""
    lower = [n.lower() for n in names]
    found: list[int | None] = []
    for aliases in candidates:
        found.append(next((lower.index(a) for a in aliases if a in lower), None))
    return found


def colors_to_uint8(channels: np.ndarray) -> np.ndarray:
    """Convert (N, 3|4) colour channels of any numeric type to uint8.

    Integers up to 255 are kept, larger integers are taken as 16-bit (>> 8, as in LAS);
    floats all within [0, 1] are scaled by 255, other floats are clipped to 0..255.
    """
    c = np.asarray(channels)
    if c.size == 0:
        return c.astype(np.uint8)
    if np.issubdtype(c.dtype, np.floating):
        finite = c[np.isfinite(c)]
        if finite.size and finite.min() >= 0.0 and finite.max() <= 1.0:
            c = c * 255.0
        return np.clip(np.rint(np.nan_to_num(c)), 0, 255).astype(np.uint8)
    if c.max() > 255:
        c = c.astype(np.int64) >> 8
    return np.clip(c, 0, 255).astype(np.uint8)


def native(a: np.ndarray) -> np.ndarray:
    """Return a contiguous copy of `a` in native byte order (structured-array fields are views)."""
    return np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("="))


def loadtxt(lines: list[str], **kwargs) -> np.ndarray:
    """np.loadtxt of text lines into an (n, k) float64 table, without its empty-input warning.

    Raises ValueError (callers turn it into FormatError) for non-numbers or ragged rows.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return np.loadtxt(lines, dtype=np.float64, ndmin=2, **kwargs)


def decode_text(data: bytes, name: str, kind: str) -> str:
    """Decode a text file (a UTF-8 byte-order mark is dropped); NUL bytes mean binary garbage."""
    if b"\0" in data[:65536]:
        raise FormatError(f"{kind} file '{name}' contains binary data, not text.")
    return data.decode("utf-8-sig", errors="replace")


def is_number(word: str) -> bool:
    """True when float() accepts `word`."""
    try:
        float(word)
    except ValueError:
        return False
    return True
