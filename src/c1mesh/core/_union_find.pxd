# Union-find over an int64 parent array (parent[i] == i at a root), shared by the kernels
# that group items: the height field's merges, the trim's connected sets of triangles, the
# report's pieces (cimported, inlined into each; nothing is compiled from this file).
from libc.stdint cimport int64_t


cdef inline int64_t root(int64_t *parent, int64_t i) noexcept nogil:
    """The root of i's set, halving the path on the way."""
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i
