# A stable counting sort of small integer keys, shared by the kernels that sort points into
# cells or buckets: the height fit's grid (plane_grid), the lattice's nearest-point buckets,
# the order CDT is given the points in (engine/_ties.pyx cell_order)
# (cimported, inlined into each; nothing is compiled from this file).
from libc.stdint cimport int64_t


cdef inline void stable_order(const int64_t *key, Py_ssize_t n, int64_t *start, Py_ssize_t keys,
                              int64_t *order) noexcept nogil:
    """order[0:n]: the indices of key[0:n] (each in [0, keys)) sorted by key, equal keys in
    index order (numpy's argsort(kind="stable")); start[0:keys + 1]: each key's first slot,
    start[keys] = n. O(n + keys), one thread."""
    cdef Py_ssize_t i
    cdef int64_t slot
    for i in range(keys + 1):
        start[i] = 0
    for i in range(n):
        start[key[i] + 1] += 1
    for i in range(keys):
        start[i + 1] += start[i]
    for i in range(n):
        slot = start[key[i]]
        order[slot] = i
        start[key[i]] = slot + 1
    for i in range(keys, 0, -1):          # each key's end back to its start
        start[i] = start[i - 1]
    start[0] = 0
