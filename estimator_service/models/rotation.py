"""The one body-to-world rotation of the estimator's parametric models: ``Rz(psi) Ry(theta)
Rx(phi)`` of roll ``phi``, pitch ``theta`` and yaw ``psi`` (the simulator's
``gpbf_env.camera.euler_to_matrix``; a test pins the two together)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["euler_matrix", "euler_rows"]

Rows = tuple[tuple[NDArray, NDArray, NDArray], ...]


def euler_rows(sin: NDArray, cos: NDArray) -> Rows:
    """The rotation's rows as three triples of arrays, from the sines and cosines ``(3, ...)``
    of roll, pitch and yaw (real or complex, for complex-step derivatives; the caller's
    sines and cosines serve its other uses too)."""
    (sf, st, sp), (cf, ct, cp) = sin, cos
    return (
        (cp * ct, cp * st * sf - sp * cf, cp * st * cf + sp * sf),
        (sp * ct, sp * st * sf + cp * cf, sp * st * cf - cp * sf),
        (-st, ct * sf, ct * cf),
    )


def euler_matrix(euler: NDArray) -> NDArray:
    """Rotation matrices ``(M, 3, 3)`` of angles ``euler (M, 3)``."""
    angles = np.asarray(euler).T
    rows = euler_rows(np.sin(angles), np.cos(angles))
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)
