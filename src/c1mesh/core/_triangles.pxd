# Plane triangle geometry shared by the kernels of several layers (cimported, inlined into
# each; nothing is compiled from this file on its own).
from libc.stdint cimport int64_t


cdef inline void corner_offsets(const double[:, ::1] xy, const int64_t[:, ::1] triangles, Py_ssize_t t,
                                double* out) noexcept nogil:
    """out[0:6] = (x0, y0, ax, ay, bx, by) for triangle t (corners i, j, k into xy (n, 2)):
    its first corner (x0, y0), and the offsets a = p_j - p_i and b = p_k - p_i of the other
    two, the frame of a triangle's circumcentre and twice its signed area."""
    out[0] = xy[triangles[t, 0], 0]
    out[1] = xy[triangles[t, 0], 1]
    out[2] = xy[triangles[t, 1], 0] - out[0]
    out[3] = xy[triangles[t, 1], 1] - out[1]
    out[4] = xy[triangles[t, 2], 0] - out[0]
    out[5] = xy[triangles[t, 2], 1] - out[1]
