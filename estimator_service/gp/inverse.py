"""Exact-GP predictive variances from explicit inverse Cholesky factors, stored as row blocks.

The latent variance at a query is ``sf2 - |L^-1 k|^2``. With ``L^-1`` computed once (see
:func:`~estimator_service.gp.linalg.inverse_factor` for when it is accurate enough), the
triangular solve becomes matrix products, and the products of all outputs can be stacked.
``L^-1`` is kept as ``B`` row blocks, each contiguous and stacked over outputs: rows
``r0:r1`` of every output's factor, columns ``:r1`` (the rest of the rows is zero). That
holds ``(B + 1) / (2B)`` of the square (7/12 for six blocks), and one step of a batched
filter reads the blocks once, in a few stacked products, whatever the number of outputs.

Cold caches make this memory-bound: a batched filter step reads every factor once between
simulator steps (measured: docs/measurements.md#inverse-factor-row-blocks).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from estimator_service.gp.linalg import blas_threads
from estimator_service.gp.parallel import over_outputs
from estimator_service.reprs import short_repr

__all__ = ["BLOCKS", "THREADED_MIN_BYTES", "InverseBlocks"]

FloatArray = NDArray[np.float64]

#: blocks bytes from which :meth:`InverseBlocks.sq_norms_threaded` splits the outputs over
#: the BLAS threads (measured: docs/measurements.md#inverse-factor-row-blocks)
THREADED_MIN_BYTES = 16 * 2**20
#: row blocks of ``L^-1`` (measured: docs/measurements.md#inverse-factor-row-blocks)
BLOCKS = 6


@dataclass(frozen=True, eq=False)
class InverseBlocks:
    """Every output's ``L^-1`` as stacked contiguous row blocks.

    Attributes
    ----------
    blocks
        Block ``b``: ``(P, r1 - r0, r1)``, rows ``r0:r1`` and columns ``:r1`` of each output's
        lower-triangular ``L^-1`` (zero for outputs without a factor).
    edges
        Row edges ``0 = e_0 < ... < e_B = n``.
    has_factor: (P,)
        Outputs whose factor is held; the others are left to the caller's solve.
    """

    __repr__ = short_repr

    blocks: tuple[FloatArray, ...]
    edges: tuple[int, ...]
    has_factor: NDArray[np.bool_]

    @classmethod
    def from_factors(
        cls, factors: Iterable[FloatArray | None], outputs: int, n: int, blocks: int = BLOCKS
    ) -> InverseBlocks:
        """From ``outputs`` per-output lower factors ``(n, n)`` or None (no factor for that
        output), taken one at a time: a generator of factors never holds more than one."""
        edges = tuple(int(e) for e in np.linspace(0, n, max(1, min(blocks, n)) + 1))
        parts = [np.zeros((outputs, r1 - r0, r1)) for r0, r1 in itertools.pairwise(edges)]
        has = np.zeros(outputs, dtype=bool)
        for p, f in enumerate(itertools.islice(factors, outputs)):
            if f is None:
                continue
            has[p] = True
            for (r0, r1), part in zip(itertools.pairwise(edges), parts, strict=True):
                part[p] = f[r0:r1, :r1]
        for arr in (*parts, has):
            arr.flags.writeable = False
        return cls(tuple(parts), edges, has)

    @property
    def nbytes(self) -> int:
        """Bytes held (and read by one call of :meth:`sq_norms`)."""
        return sum(b.nbytes for b in self.blocks)

    def sq_norms(self, ks: FloatArray, outputs: slice = slice(None)) -> FloatArray:
        """``|L_p^-1 k_pq|^2 (P', M)`` for the outputs ``p`` in ``outputs`` (all by default)
        from their kernel rows ``ks (P', M, n)`` (zero for outputs without a factor): one
        stacked product per block."""
        out = np.zeros(ks.shape[:2])
        for r1, part in zip(self.edges[1:], self.blocks, strict=True):
            v = ks[:, :, :r1] @ part[outputs].transpose(0, 2, 1)  # (P', M, rows)
            out += np.einsum("pqr,pqr->pq", v, v)
        return out

    def sq_norms_threaded(self, ks: FloatArray) -> FloatArray:
        """:meth:`sq_norms` of all outputs, split into one group of outputs per BLAS thread
        when the blocks are large enough to pay for the threads
        (:data:`THREADED_MIN_BYTES`); the result does not depend on the split."""
        p_out = ks.shape[0]
        w = min(blas_threads(), p_out)
        if w <= 1 or self.nbytes < THREADED_MIN_BYTES:
            return self.sq_norms(ks)
        out = np.empty(ks.shape[:2])
        edges = np.linspace(0, p_out, w + 1).astype(int)

        def group(i: int) -> None:
            sl = slice(edges[i], edges[i + 1])
            out[sl] = self.sq_norms(ks[sl], sl)

        over_outputs(group, w)
        return out
