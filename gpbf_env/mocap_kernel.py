"""Compiled kernels of :mod:`gpbf_env.mocap`: pose rates at the RK4 knots and the
motion-capture fit, scalar code per blimp (numba) with the array code's operations."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from gpbf_env.dynamics import wrap_angle
from gpbf_env.jit import kernel

__all__ = ["measure_kernel", "pose_rates"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@kernel
def pose_rates(knots: FloatArray, out: FloatArray) -> None:
    """World-frame velocity and Euler-angle rates ``out`` (K, 6, N) of states ``knots`` (K, 12, N)."""
    for j in range(knots.shape[0]):
        for b in range(knots.shape[2]):
            phi, th, psi = knots[j, 3, b], knots[j, 4, b], knots[j, 5, b]
            u, v, w = knots[j, 6, b], knots[j, 7, b], knots[j, 8, b]
            p, q, r = knots[j, 9, b], knots[j, 10, b], knots[j, 11, b]
            sf, cf, st, ct = math.sin(phi), math.cos(phi), math.sin(th), math.cos(th)
            sp, cp = math.sin(psi), math.cos(psi)
            tq = (q * sf + r * cf) / ct
            a, c = st * sf, st * cf  # shared factors of the rotation's rows
            out[j, 0, b] = cp * ct * u + (cp * a - sp * cf) * v + (cp * c + sp * sf) * w
            out[j, 1, b] = sp * ct * u + (sp * a + cp * cf) * v + (sp * c - cp * sf) * w
            out[j, 2, b] = -st * u + ct * sf * v + ct * cf * w
            out[j, 3, b] = p + st * tq
            out[j, 4, b] = q * cf - r * sf
            out[j, 5, b] = tq


@kernel
def measure_kernel(
    buf: FloatArray, at: IntArray, weights: FloatArray, noise: FloatArray, std: FloatArray,
    slope: FloatArray, out: FloatArray,
) -> None:  # fmt: skip
    """Motion-capture states ``out`` (N, 12) from a pose track.

    ``buf`` (depth, n_sub + 1, 12, N) is the track; the slope of the noiseless samples
    is ``sum weights[l, 0] pose + weights[l, 1] rate`` over the knots ``at[l]``
    (step back, knot); ``noise`` (N, >= 6 M) standard normals, scaled by ``std`` (6,),
    perturb the M samples, whose least-squares slope weights are ``slope`` (M,).
    """
    pose, d = np.empty(6), np.empty(6)
    for b in range(buf.shape[3]):
        for i in range(6):
            now = buf[0, buf.shape[1] - 1, i, b]
            pose[i] = (wrap_angle(now) if i >= 3 else now) + noise[b, i] * std[i]
            if i >= 3:
                pose[i] = wrap_angle(pose[i])
            acc = 0.0
            for ell in range(at.shape[0]):
                knot = buf[at[ell, 0], at[ell, 1], :, b]
                acc += weights[ell, 0] * knot[i] + weights[ell, 1] * knot[6 + i]
            for m in range(slope.shape[0]):
                acc = acc + slope[m] * (noise[b, 6 * m + i] * std[i])
            d[i] = acc
        sf, cf, st, ct = math.sin(pose[3]), math.cos(pose[3]), math.sin(pose[4]), math.cos(pose[4])
        sp, cp = math.sin(pose[5]), math.cos(pose[5])
        rot = ((cp * ct, cp * st * sf - sp * cf, cp * st * cf + sp * sf),
               (sp * ct, sp * st * sf + cp * cf, sp * st * cf - cp * sf),
               (-st, ct * sf, ct * cf))  # fmt: skip
        for i in range(6):
            out[b, i] = pose[i]
        for j in range(3):
            out[b, 6 + j] = rot[0][j] * d[0] + rot[1][j] * d[1] + rot[2][j] * d[2]
        out[b, 9] = d[3] - st * d[5]
        out[b, 10] = cf * d[4] + sf * ct * d[5]
        out[b, 11] = -sf * d[4] + cf * ct * d[5]
