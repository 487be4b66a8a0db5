# cython: language_level=3
"""The radix selection's kernels: c1mesh.stages.streamed_median wraps them (validation, the
passes), and nothing else imports them. A value's order key is its float64 bit pattern
read as uint64, the sign bit flipped for non-negative values and every bit flipped for
negative ones, so keys order as the values do; the kernels make each key as they read its
value, so no key array is stored."""
from libc.stdint cimport int64_t, uint64_t
from libc.string cimport memcpy

cdef uint64_t _SIGN = (<uint64_t>1) << 63


cdef inline uint64_t _key(double value) noexcept nogil:
    """The order key of value (module docstring)."""
    cdef uint64_t bits
    memcpy(&bits, &value, 8)
    if bits & _SIGN:
        return ~bits
    return bits | _SIGN


cdef inline bint _in_bin(uint64_t key, uint64_t prefix, int known) noexcept nogil:
    """Whether key's top `known` bits are prefix's (every key when known is 0)."""
    return known == 0 or (key >> (64 - known)) == (prefix >> (64 - known))


def bin_histogram(const double[:] values, uint64_t prefix, int known, int bits, int64_t[::1] histogram):
    """Add to histogram (2**bits,) the count of each next `bits` bits (below the top
    `known`) of the keys of values (m,) whose top `known` bits are prefix's. Without the
    GIL; known + bits <= 64."""
    cdef Py_ssize_t i
    cdef uint64_t key, mask = ((<uint64_t>1) << bits) - 1
    cdef int shift = 64 - known - bits
    with nogil:
        for i in range(values.shape[0]):
            key = _key(values[i])
            if _in_bin(key, prefix, known):
                histogram[(key >> shift) & mask] += 1


def gather_bin(const double[:] values, uint64_t prefix, int known, uint64_t[::1] out):
    """Write to out the keys of values (m,) whose top `known` bits are prefix's, in order;
    returns how many (out must hold them all). Without the GIL."""
    cdef Py_ssize_t i, count = 0
    cdef uint64_t key
    with nogil:
        for i in range(values.shape[0]):
            key = _key(values[i])
            if _in_bin(key, prefix, known):
                out[count] = key
                count += 1
    return count
