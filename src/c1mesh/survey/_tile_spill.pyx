# cython: language_level=3
"""The spill's read kernels: c1mesh.survey.tile_spill wraps them, and nothing else imports them."""
from libc.stdint cimport int64_t, uint8_t


def in_rect(const double[:] x, const double[:] y, double x0, double y0, double x1, double y1,
            uint8_t[::1] out):
    """out[i] = whether (x[i], y[i]) lies in the closed rectangle [x0, x1] × [y0, y1] (a NaN
    coordinate does not), for the records' x and y fields (m,), strided views of a spill
    file's rows; returns how many do. One pass over the rows where numpy's four comparisons
    and three ands made seven. Without the GIL."""
    cdef Py_ssize_t i, count = 0
    cdef double xi, yi
    cdef uint8_t inside
    with nogil:
        for i in range(x.shape[0]):
            xi = x[i]
            yi = y[i]
            inside = xi >= x0 and xi <= x1 and yi >= y0 and yi <= y1
            out[i] = inside
            count += inside
    return count


cdef inline void _copy(uint8_t *to, const uint8_t *source, Py_ssize_t words) noexcept nogil:
    """Copy one record of `words` 8-byte words."""
    cdef Py_ssize_t w
    for w in range(words):
        (<int64_t *> to)[w] = (<const int64_t *> source)[w]


def merge_two(const uint8_t[:, ::1] a, const uint8_t[:, ::1] b, uint8_t[:, ::1] out):
    """Merge two record arrays (rows of `size` bytes, a multiple of 8, whose first 8 bytes
    are an int64 survey number, strictly ascending within each) into out (len a + len b,
    size), ascending. Returns False, out then unspecified, when a number repeats or
    descends (the caller sorts instead). One comparison and one record copy a row."""
    cdef Py_ssize_t na = a.shape[0], nb = b.shape[0], size = out.shape[1], words = size // 8
    cdef Py_ssize_t i = 0, j = 0, o = 0
    cdef int64_t ka, last
    cdef const uint8_t *pa
    cdef const uint8_t *pb
    cdef uint8_t *po
    cdef bint ok = True
    if a.shape[1] != size or b.shape[1] != size or size % 8 or out.shape[0] != na + nb:
        raise ValueError("merge_two needs records of one size, a multiple of 8 bytes, and room for both")
    if na + nb == 0:
        return True
    pa = &a[0, 0] if na else NULL
    pb = &b[0, 0] if nb else NULL
    po = &out[0, 0]
    with nogil:
        last = 0
        while i < na or j < nb:
            if j == nb or (i < na and (<const int64_t *> (pa + i * size))[0] < (<const int64_t *> (pb + j * size))[0]):
                _copy(po + o * size, pa + i * size, words)
                i += 1
            else:
                _copy(po + o * size, pb + j * size, words)
                j += 1
            ka = (<const int64_t *> (po + o * size))[0]
            if o and ka <= last:
                ok = False
                break
            last = ka
            o += 1
    return ok
