"""LZF decompression (the liblzf format PCL uses for `DATA binary_compressed`).

The stream is a sequence of tokens, each starting with a control byte `c`:
  c < 32:  a literal run; copy the next c + 1 input bytes to the output.
  c >= 32: a back reference; length L = c >> 5 (if 7, add the next byte), offset
           D = ((c & 31) << 8) + next byte + 1; copy L + 2 bytes starting D bytes back in
           the output. The ranges may overlap (D < L + 2): then the last D bytes repeat.
Pure Python: one loop iteration per token (at most 32 literal or 264 copied bytes),
which decodes ~20 MB of point data in well under a couple of seconds.
"""
from __future__ import annotations


class LZFError(ValueError):
    """The compressed stream is corrupt or does not decode to the promised size."""


def lzf_decompress(src: bytes, out_len: int) -> bytearray:
    """Decompress LZF stream `src` into exactly `out_len` bytes, or raise LZFError."""
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
