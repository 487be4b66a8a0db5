# The orders of c1mesh.engine.rsd's PAIRS and PERMS, for the kernels that index the RSD
# coefficients (engine/_rsd.pyx, stages/_smoothing_energy.pyx): cimported and inlined,
# so both read the same tables as the Python module states them.


cdef inline void rsd_orders(int *pair_k, int *pair_i, int *perm_l, int *perm_m, int *perm_n) noexcept nogil:
    """Fill (6,) each: PAIRS (k, i), i != k, the columns 3..8 of the coefficients
    (g_ki = A_k · (p_i − p_k)); PERMS (l, m, n), the columns 9..14 and 15..20."""
    cdef int j
    cdef int k_of[6]
    cdef int i_of[6]
    cdef int n_of[6]
    k_of[:] = [0, 0, 1, 1, 2, 2]
    i_of[:] = [1, 2, 0, 2, 0, 1]
    n_of[:] = [2, 1, 2, 0, 1, 0]
    for j in range(6):
        pair_k[j] = k_of[j]
        pair_i[j] = i_of[j]
        perm_l[j] = k_of[j]         # PERMS' l and m run as PAIRS' k and i
        perm_m[j] = i_of[j]
        perm_n[j] = n_of[j]
