# cython: language_level=3
"""The refined surface's kernel: c1mesh.stages.surface wraps it (validation, blocks), and
nothing else imports it.

A height field's refined points come as plane positions (x, y), spline values z and
gradients (fx, fy) in the frame; the writers want world vertices and unit normals. numpy
did that in four passes (the BLAS product of to_world, gradients_to_normals, the BLAS
product of vectors_to_world, with a (n, 3) temporary): 66 ns a point, 1 s of a 16M-vertex
output. This is one pass, 15 ns a point, with the same bits:

* OpenBLAS's dgemm (the kernel numpy's matmul reaches on x86-64 CPUs with FMA) sums each
  output element over k in order with fused multiply-adds: acc = a0 b0, then
  acc = fma(a1, b1, acc), acc = fma(a2, b2, acc). The loop below does exactly that, with
  C's fma (exact by definition, so the same on any CPU), then adds the origin as numpy's
  `+=` does.
* The unit normal (-fx, -fy, 1) / sqrt(fx² + fy² + 1) is computed with numpy's operations
  in numpy's order (height_field.gradients_to_normals); the build's -ffp-contract=off keeps
  the compiler from fusing them.

On gcc for x86-64 Linux the function is compiled twice (target_clones): once with the FMA
instruction, chosen at load time on CPUs that have it, and once calling libm's fma
(exact in software, slower). tests/test_surface_rows.py checks the bits against numpy.
"""
from libc.math cimport sqrt
from libc.stdint cimport int64_t

cdef extern from *:
    """
    #if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__)
    #define C1MESH_FMA_CLONES __attribute__((target_clones("fma", "default")))
    #else
    #define C1MESH_FMA_CLONES
    #endif

    /* rows i of (points (n, 2), values (n,), gradients (n, 2)) -> out (n, 6): the vertex
       (x, y, z) axes + origin, then the normal unit(-fx, -fy, 1) axes; axes (3, 3) row-major. */
    C1MESH_FMA_CLONES
    static void c1mesh_world_rows(int64_t n, const double *points, const double *values,
                                  const double *gradients, const double *axes,
                                  const double *origin, double *out)
    {
        for (int64_t i = 0; i < n; i++) {
            const double x = points[2 * i], y = points[2 * i + 1], z = values[i];
            const double fx = gradients[2 * i], fy = gradients[2 * i + 1];
            const double inv = 1.0 / sqrt(fx * fx + fy * fy + 1.0);
            const double a = fx * -inv, b = fy * -inv, c = inv;
            for (int j = 0; j < 3; j++) {
                double at = x * axes[j];
                at = __builtin_fma(y, axes[3 + j], at);
                at = __builtin_fma(z, axes[6 + j], at);
                out[6 * i + j] = at + origin[j];
                double along = a * axes[j];
                along = __builtin_fma(b, axes[3 + j], along);
                along = __builtin_fma(c, axes[6 + j], along);
                out[6 * i + 3 + j] = along;
            }
        }
    }
    """
    void c1mesh_world_rows(int64_t n, const double *points, const double *values,
                           const double *gradients, const double *axes, const double *origin,
                           double *out) nogil


def world_rows(const double[:, ::1] points, const double[::1] values, const double[:, ::1] gradients,
               const double[:, ::1] axes, const double[::1] origin, double[:, ::1] out):
    """out[i, :3] = (points[i, 0], points[i, 1], values[i]) · axes + origin and out[i, 3:]
    = the unit upward normal of gradients[i] (local) · axes, for every row of points (n, 2);
    the frame's axes (3, 3) rows e1, e2, e3 and origin (3,), world units; out (n, 6), the
    rows of a PLY with normals. Without the GIL."""
    cdef int64_t n = points.shape[0]
    if n == 0:
        return
    with nogil:
        c1mesh_world_rows(n, &points[0, 0], &values[0], &gradients[0, 0], &axes[0, 0], &origin[0],
                          &out[0, 0])
