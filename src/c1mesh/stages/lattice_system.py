"""The smoothing system of a lattice mesh, assembled straight into the lattice solver's stencil form (issue 38).

On a lattice mesh (stages.lattice_solver: the vertices on grid nodes, every cell split by
its (i, j)-(i+1, j+1) diagonal) every triangle is a translate of a few shapes
(smoothing_system.TriangleShapes), whose 9 × 9 energy blocks serve them all, and every
entry of

    S = A^T W A + s K + μ P      (smoothing_system's notation, normalised units)

couples a vertex to one of its 7 stencil neighbours. `LatticeSystem.stencil` writes S
for a strength s straight into the solver's Stencil by halves (4, N, 3, 3: each vertex's
blocks at itself and its 3 forward neighbours; the backward ones are their transposes):
no whole-survey K or S as CSR (0.75 GB each at 1M vertices), nor all 7 blocks (0.51 GB;
the halves 0.29). The kernels (_lattice_system.assemble_data, then assemble_energy) write
each vertex's own rows against itself and its forward neighbours from the triangles at it
and their data points, the vertices in fixed blocks in the thread knob's threads; the
data term's pass needs no s, so smooth_fit runs it during the strength search
(`data_term_ahead`). Each entry is summed
in the order the CSR assembly summed it (K over the triangles in increasing order, then
s K plus the data term over the triangles' points in order), so the stored blocks have
the bits of System.matrix's entries there, and they do not depend on the thread count.
System.matrix's other half (the backward blocks, summed at the other vertex with the
products in the other order) differs from their transposes in the last bits: the
lattice route's S is System.matrix's to rounding, and exactly symmetric off its
diagonal blocks (those are System.matrix's, as assembled).

The data rows are smoothing_system.DataRows (A u and Aᵀ r by its kernels, for the rhs,
the residuals and the edf's probes).
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np

from c1mesh.core.threads import blocks_ahead, parallel_blocks
from c1mesh.stages import _lattice_system as kernel
from c1mesh.stages.lattice_solver import HALF, Stencil
from c1mesh.stages.smoothing_energy import N_LOCAL, SmoothingError
from c1mesh.stages.smoothing_system import (DataRows, data_adjoint, data_fitted, gradient_terms,
                                            incidence)

ASSEMBLY_BLOCK = 1 << 14
"""Vertices per block of the energy's pass of the stencil assembly (in the thread knob's threads)."""
DATA_BLOCK = 1 << 16
"""Vertices per block of the data term's pass (LatticeSystem.data_term_ahead), which a
background thread takes during the strength search: about 85 ms of work each at 1M data
(1.3 µs a vertex), long against the GIL a block's return waits for while the search's
factorisation holds it (31 ms at most on the DTM job)."""


@dataclass
class LatticeSystem:
    """The pieces of S on a lattice mesh that do not change with s or the weights.

    triangles (T, 3) int64 over the N vertices; shape_of (T,) int64 each triangle's shape,
    elements (k, 9, 9) each shape's energy block (smoothing_energy's local order); nbr
    (N, 7) int32 each vertex's stencil neighbours (lattice_solver.stencil_neighbours, the
    vertices numbered as the solver's fine level numbers them). data: the data rows
    (DataRows), or None when the data are the vertices; z (M,) the data values; grad_mask
    (N,) 1.0 at vertices with gradient data grad_values (N, 2), or None."""

    triangles: np.ndarray
    shape_of: np.ndarray
    elements: np.ndarray
    nbr: np.ndarray
    data: DataRows | None
    z: np.ndarray
    grad_mask: np.ndarray | None = None
    grad_values: np.ndarray | None = None

    @property
    def n_unknowns(self) -> int:
        return 3 * self.nbr.shape[0]

    def fitted(self, u: np.ndarray) -> np.ndarray:
        """F at the data points (M,) for unknowns u (3N,); (M, k) for k columns u (3N, k)."""
        return data_fitted(self.data, u)

    def adjoint(self, r: np.ndarray) -> np.ndarray:
        """A^T r (3N,) for r (M,); (3N, k) for k columns r (M, k)."""
        return data_adjoint(self.data, r, self.n_unknowns)

    def stencil(self, s: float, w: np.ndarray, mu: float) -> tuple[Stencil, np.ndarray]:
        """(S in stencil form, rhs (3N,)) for strength s, data weights w (M,) and gradient
        weight mu (System.matrix's S to rounding: its self and forward blocks' bits, the
        backward ones their transposes; its rhs, the same bits). SmoothingError when a
        triangle's corners are not stencil neighbours (cells split by the other diagonal,
        or nbr not the triangles' lattice)."""
        with self.data_term_ahead(w, mu) as data:
            return self.with_strength(s, data())

    @contextlib.contextmanager
    def data_term_ahead(self, w: np.ndarray, mu: float) -> Iterator[Callable[[], "DataTerm"]]:
        """The DataTerm of weights w (M,) and gradient weight mu, begun in a background
        thread while the block runs (core.threads.blocks_ahead: first the corners at each
        vertex, the points by triangle and the rhs, then the data blocks); yields the call
        that finishes it in the caller's threads and returns it. smooth_fit sums it during
        the strength search, whose direct factorisations leave a core idle: it needs no s."""
        w = np.ascontiguousarray(w, dtype=np.float64)
        blocks = np.empty((len(HALF), self.nbr.shape[0], 3, 3))
        made: dict = {}
        outside: list = []

        def prepare() -> None:             # the corners at each vertex, the points by triangle
            made["start"], made["corner"] = incidence(self.triangles, self.nbr.shape[0])
            if self.data is None:                          # the data are the vertices: on diag
                made["first"] = np.zeros(self.triangles.shape[0] + 1, dtype=np.int64)
                made["points"], made["rows"] = np.empty(0, dtype=np.int64), np.empty((0, N_LOCAL))
            else:
                made["first"], made["points"] = self.data.points_by_triangle()
                made["rows"] = np.ascontiguousarray(self.data.values, dtype=np.float64)
            made["rhs"], made["diag"] = self._right_side(w, mu)

        def work(part: slice) -> None:
            outside.append(kernel.assemble_data(self.triangles, made["start"], made["corner"], made["first"],
                                                made["points"], made["rows"], w, self.nbr, blocks,
                                                part.start, part.stop))
        with blocks_ahead(work, self.nbr.shape[0], DATA_BLOCK, prepare) as finish:
            def finished() -> DataTerm:
                finish()
                _check_outside(sum(outside))
                return DataTerm(blocks, made["rhs"], made["diag"], made["start"], made["corner"])
            yield finished

    def _right_side(self, w: np.ndarray, mu: float) -> tuple[np.ndarray, np.ndarray]:
        """(rhs (3N,): Aᵀ W z plus the gradient data's pull, diag (N, 3): what S's diagonal
        takes after the rest, the vertex data's weights and the gradient weights)."""
        rhs = self.adjoint(w * self.z)
        diag = np.zeros((self.nbr.shape[0], 3))
        if self.data is None:
            diag[:, 0] = w
        gradients = gradient_terms(self.grad_mask, self.grad_values, mu)
        if gradients is not None:
            weight, pull = gradients
            diag[:, 1] = diag[:, 2] = weight
            rhs[1::3] += pull[:, 0]
            rhs[2::3] += pull[:, 1]
        return rhs, diag

    def with_strength(self, s: float, data: "DataTerm") -> tuple[Stencil, np.ndarray]:
        """(S's Stencil, rhs) for strength s from the DataTerm `data`, whose blocks become
        S's (s K summed into them in place, vertices in fixed blocks of ASSEMBLY_BLOCK in
        the thread knob's threads; `data` is spent)."""
        self._energy_pass(data, self.shape_of, self.elements, s, data.diag, data.blocks)
        return Stencil(self.nbr, data.blocks), data.rhs

    def stiffen(self, stencil: Stencil, s: float, data: "DataTerm", extra: np.ndarray) -> None:
        """Add s Σ_t extra[t] K_t to the Stencil `stencil` (with_strength's, from `data`), in
        place: triangle t's energy weighs 1 + extra[t] times as much as before (extra (T,) >= 0;
        stages.folds' net, which stiffens the cells where a fit folds). The energy kernel
        sums the extra blocks (each shape's scaled by its triangles' factor, zero elsewhere)
        and adds them, times s, to every vertex's blocks."""
        extra = np.asarray(extra, dtype=np.float64)
        factors = np.unique(extra[extra > 0])
        shapes = self.elements.shape[0]
        elements = np.concatenate([np.zeros_like(self.elements)] + [self.elements * factor for factor in factors])
        shape_of = self.shape_of.copy()
        stiff = extra > 0
        shape_of[stiff] += shapes * (np.searchsorted(factors, extra[stiff]) + 1)
        self._energy_pass(data, shape_of, elements, s, np.zeros((self.nbr.shape[0], 3)), stencil.blocks)

    def _energy_pass(self, data: "DataTerm", shape_of: np.ndarray, elements: np.ndarray, s: float,
                     diag: np.ndarray, blocks: np.ndarray) -> None:
        """blocks += s × the energy of triangle shapes shape_of (T,) with blocks elements
        (k, 9, 9), plus diag (N, 3) on the diagonal (_lattice_system.assemble_energy), the
        vertices in fixed blocks of ASSEMBLY_BLOCK in the thread knob's threads, over the
        corners at each vertex that data (a DataTerm) holds."""
        elements = np.ascontiguousarray(elements, dtype=np.float64)
        outside: list = []
        parallel_blocks(lambda part: outside.append(kernel.assemble_energy(
            self.triangles, data.start, data.corner, shape_of, elements, self.nbr, float(s), diag,
            blocks, part.start, part.stop)), self.nbr.shape[0], ASSEMBLY_BLOCK)
        _check_outside(sum(outside))


@dataclass(frozen=True)
class DataTerm:
    """The part of a lattice system that needs no strength (LatticeSystem.data_term_ahead):
    blocks (4, N, 3, 3) the data term Aᵀ W A's stored half (_lattice_system.assemble_data),
    rhs (3N,), diag (N, 3) (LatticeSystem._right_side), and the triangle corners at each
    vertex (start, corner: smoothing_system.incidence) the energy's pass reads again."""

    blocks: np.ndarray
    rhs: np.ndarray
    diag: np.ndarray
    start: np.ndarray
    corner: np.ndarray


def _check_outside(count: int) -> None:
    """SmoothingError when `count` triangle corners were not stencil neighbours."""
    if count:
        raise SmoothingError(f"the system is not on the lattice's stencil: {count} triangle corners "
                             "are not stencil neighbours of another corner (cells split by the other "
                             "diagonal, or nodes that are not the vertices' own?)")


__all__ = ["LatticeSystem", "DataTerm", "ASSEMBLY_BLOCK", "DATA_BLOCK"]
