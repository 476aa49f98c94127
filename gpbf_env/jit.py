"""The one compilation setting of the simulator's numba kernels.

``cache=True`` stores the machine code beside the modules (or in the user's cache when
the package is read-only), so only the first process on a machine compiles (seconds);
``error_model="numpy"`` makes a division by zero give inf or nan as the array code did,
instead of raising.
"""

from __future__ import annotations

from numba import njit

__all__ = ["kernel"]

kernel = njit(cache=True, error_model="numpy")
