"""LZF decompression (the liblzf format PCL uses for `DATA binary_compressed`).

The stream is a sequence of tokens, each starting with a control byte `c`:
  c < 32:  a literal run; copy the next c + 1 input bytes to the output.
  c >= 32: a back reference; length L = c >> 5 (if 7, add the next byte), offset
           D = ((c & 31) << 8) + next byte + 1; copy L + 2 bytes starting D bytes back in
           the output. The ranges may overlap (D < L + 2): then the last D bytes repeat.
Each token of at most 3 input bytes yields at most 264 output bytes, so a stream of n
bytes can decode to at most MAX_EXPANSION * n bytes; callers bound claims with that.

Decoding is liblzf's C decoder through python-lzf, a required dependency, called with
the promised size as its output bound, so a stream never decodes to more than that.
"""
from __future__ import annotations

import lzf as _clzf

#: Most output bytes per input byte: a 3-byte back reference copies 7 + 255 + 2 = 264.
MAX_EXPANSION = 88


class LZFError(ValueError):
    """The compressed stream is corrupt or does not decode to the promised size."""


def lzf_decompress(src: bytes, out_len: int) -> bytes:
    """Decompress LZF stream `src` into exactly `out_len` bytes, or raise LZFError.

    liblzf writes into a buffer of `out_len` bytes and stops (E2BIG) when the stream
    would go past it, so memory is bounded by the claim, which callers check first.
    """
    if out_len > MAX_EXPANSION * len(src):
        raise LZFError(f"{len(src)} compressed bytes cannot decode to {out_len}")
    if out_len == 0:
        if src:
            raise LZFError(f"stream of {len(src)} bytes decodes to more than the promised 0 bytes")
        return b""
    try:
        out = _clzf.decompress(src, out_len)
    except ValueError as exc:   # liblzf's EINVAL: a corrupt token
        raise LZFError(f"corrupt stream ({exc})") from None
    if out is None:             # E2BIG: the stream decodes to more than out_len bytes
        raise LZFError(f"stream decodes to more than the promised {out_len} bytes")
    if len(out) != out_len:
        raise LZFError(f"stream decodes to {len(out)} bytes, not the promised {out_len}")
    return out
