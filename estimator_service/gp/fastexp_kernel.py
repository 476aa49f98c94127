"""The compiled loop of :mod:`estimator_service.gp.fastexp` (numba; imported on first use).

``exp(x) = 2^k exp(r)``, ``k = round(x / ln 2)``, ``r = x - k ln 2`` with ``ln 2`` in two
parts (Cody and Waite), so ``|r| <= ln(2) / 2``; ``exp(r)`` by its Taylor polynomial of
degree 13 (truncation error at most ``|r|^14 / 14! < 5e-18``, a fortieth of an ulp),
Horner's rule with fused multiply-adds; ``2^k`` from its exponent bits in two factors
``2^(k // 2)`` and ``2^(k - k // 2)``, so that neither leaves the float64 range for ``k``
from -1075 to 1024 and the product rounds once into the subnormals or to infinity as
``exp`` does. The rounding to an integer adds and subtracts ``1.5 * 2^52``; the
conversions are to 32-bit integers, which AVX2 has (it lacks the 64-bit ones), so the loop
vectorises there. Measured over the whole float64 range: within 1 ulp of NumPy's ``exp``;
NaN stays NaN, ``-inf`` gives 0, ``inf`` gives inf.

Kept apart so that a process that never exponentiates a large block does not import numba
(about 0.5 s) nor load the compiled code (about 0.2 s from numba's cache).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numba.core import types
from numba.extending import intrinsic
from numpy.typing import NDArray

__all__ = ["exp_capped_rows"]

FloatArray = NDArray[np.float64]
LOG2E = 1.4426950408889634
LN2_HI = 6.93147180369123816490e-01  # ln 2 = LN2_HI + LN2_LO; k * LN2_HI is exact for |k| < 2^11
LN2_LO = 1.90821492927058770002e-10
SHIFTER = 6755399441055744.0  # 1.5 * 2^52: (x + SHIFTER) - SHIFTER rounds x to an integer
LOWEST, HIGHEST = -745.2, 709.8  # exp rounds to 0 below, overflows above


@intrinsic
def _as_float(typingctx, bits):
    """The float64 whose bits are the int64 ``bits``."""

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], context.get_value_type(types.float64))

    return types.float64(types.int64), codegen


@njit(cache=True, nogil=True, error_model="numpy", boundscheck=False, fastmath={"contract"})
def exp_capped_rows(rows: FloatArray, caps: FloatArray) -> None:
    """``rows (P, L)`` set to ``exp(min(rows, caps[:, None]))`` in place (C-contiguous)."""
    for j in range(rows.shape[0]):
        _exp_capped_row(rows[j], caps[j])


@njit(cache=True, nogil=True, error_model="numpy", boundscheck=False, fastmath={"contract"})
def _exp_capped_row(x: FloatArray, cap: float) -> None:
    for i in range(x.size):
        xi = x[i]
        v = xi if xi < cap else cap
        v = v if v > LOWEST else LOWEST
        v = v if v < HIGHEST else HIGHEST
        k = (v * LOG2E + SHIFTER) - SHIFTER
        r = (v - k * LN2_HI) - k * LN2_LO
        p = 1.0 / 6227020800.0
        p = p * r + 1.0 / 479001600.0
        p = p * r + 1.0 / 39916800.0
        p = p * r + 1.0 / 3628800.0
        p = p * r + 1.0 / 362880.0
        p = p * r + 1.0 / 40320.0
        p = p * r + 1.0 / 5040.0
        p = p * r + 1.0 / 720.0
        p = p * r + 1.0 / 120.0
        p = p * r + 1.0 / 24.0
        p = p * r + 1.0 / 6.0
        p = p * r + 0.5
        p = p * r + 1.0
        p = p * r + 1.0
        ki = np.int32(k)
        half = ki >> 1
        first = _as_float(np.int64(half + 1023) << 52)
        second = _as_float(np.int64(ki - half + 1023) << 52)
        x[i] = p * first * second if xi == xi else xi
