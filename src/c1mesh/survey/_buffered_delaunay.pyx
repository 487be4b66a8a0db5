# cython: language_level=3
"""The tile grid's kernel: c1mesh.survey.buffered_delaunay.TileGrid wraps it, and nothing else
imports it."""
from libc.math cimport floor
from libc.stdint cimport int64_t


cdef inline int64_t _cell(double v, double low, double width, int64_t count) noexcept nogil:
    """The column (or row) of coordinate v: floor((v − low) / width · count), clipped to
    [0, count − 1], as numpy's floor, int64 cast and clip give it for finite v (NaN: 0)."""
    cdef double k = floor((v - low) / width * count)
    if not k >= 0:
        return 0
    if k > count - 1:
        return count - 1
    return <int64_t>k


def tiles_of(const double[:] x, const double[:] y, double x0, double y0, double x1, double y1,
             int64_t nx, int64_t ny, int64_t[::1] out):
    """out[i] = the tile of point (x[i], y[i]) in the grid of nx × ny cells over the box
    (x0, y0, x1, y1): column + nx · row. x, y: (m,) finite coordinates, strided views (a
    record array's fields) welcome. One pass where numpy made ten. Without the GIL."""
    cdef Py_ssize_t i
    cdef double width = x1 - x0, height = y1 - y0
    with nogil:
        for i in range(x.shape[0]):
            out[i] = _cell(x[i], x0, width, nx) + nx * _cell(y[i], y0, height, ny)
