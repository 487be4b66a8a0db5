"""LZF decompression (the liblzf format PCL uses for `DATA binary_compressed`).

The stream is a sequence of tokens, each starting with a control byte `c`:
  c < 32:  a literal run; copy the next c + 1 input bytes to the output.
  c >= 32: a back reference; length L = c >> 5 (if 7, add the next byte), offset
           D = ((c & 31) << 8) + next byte + 1; copy L + 2 bytes starting D bytes back in
           the output. The ranges may overlap (D < L + 2): then the last D bytes repeat.
Each token of at most 3 input bytes yields at most 264 output bytes, so a stream of n
bytes can decode to at most MAX_EXPANSION * n bytes; callers bound claims with that.

`lzf_decompress` uses liblzf's C decoder (the python-lzf package) when it is installed,
and otherwise `lzf_decompress_python`, a loop with one iteration per token; the two
agree on every valid stream and both reject corrupt ones (tests/test_formats.py).
"""
from __future__ import annotations

try:
    import lzf as _clzf
except ImportError:  # python-lzf is built from source; without a compiler, decode in Python
    _clzf = None

#: Most output bytes per input byte: a 3-byte back reference copies 7 + 255 + 2 = 264.
MAX_EXPANSION = 88


class LZFError(ValueError):
    """The compressed stream is corrupt or does not decode to the promised size."""


def lzf_decompress(src: bytes, out_len: int) -> bytes | bytearray:
    """Decompress LZF stream `src` into exactly `out_len` bytes, or raise LZFError."""
    if out_len > MAX_EXPANSION * len(src):
        raise LZFError(f"{len(src)} compressed bytes cannot decode to {out_len}")
    if _clzf is None or out_len == 0:
        return lzf_decompress_python(src, out_len)
    try:
        out = _clzf.decompress(src, out_len)
    except ValueError as exc:   # liblzf's EINVAL: a corrupt token
        raise LZFError(f"corrupt stream ({exc})") from None
    if out is None:             # E2BIG: the stream decodes to more than out_len bytes
        raise LZFError(f"stream decodes to more than the promised {out_len} bytes")
    if len(out) != out_len:
        raise LZFError(f"stream decodes to {len(out)} bytes, not the promised {out_len}")
    return out


def lzf_decompress_python(src: bytes, out_len: int) -> bytearray:
    """The same decoder in pure Python (no C extension needed)."""
    out = bytearray(out_len)
    ip = op = 0
    n = len(src)
    while ip < n:
        ctrl = src[ip]
        ip += 1
        if ctrl < 32:
            length = ctrl + 1
            if ip + length > n or op + length > out_len:
                raise LZFError(f"literal run of {length} bytes at input offset {ip - 1} runs past the end")
            out[op:op + length] = src[ip:ip + length]
            ip += length
            op += length
            continue
        length = ctrl >> 5
        if ip + (length == 7) >= n:
            raise LZFError(f"back reference at input offset {ip - 1} is cut off")
        if length == 7:
            length += src[ip]
            ip += 1
        ref = op - ((ctrl & 0x1F) << 8) - src[ip] - 1
        ip += 1
        length += 2
        if ref < 0 or op + length > out_len:
            raise LZFError(f"back reference at input offset {ip} points outside the output")
        if ref + length <= op:
            out[op:op + length] = out[ref:ref + length]
        else:  # overlapping copy: the period op - ref pattern repeats
            period = out[ref:op]
            out[op:op + length] = (period * (length // len(period) + 1))[:length]
        op += length
    if op != out_len:
        raise LZFError(f"stream decodes to {op} bytes, not the promised {out_len}")
    return out
