"""Compiled kernels of :mod:`gpbf_env.mocap`: pose rates at the RK4 knots and the
motion-capture fit, scalar code per blimp (numba) with the array code's operations."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gpbf_env.dynamics import rotation, wrap_angle
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
            r11, r12, r13, r21, r22, r23, r31, r32, r33, sf, cf, st, ct = rotation(phi, th, psi)
            tq = (q * sf + r * cf) / ct
            out[j, 0, b] = r11 * u + r12 * v + r13 * w
            out[j, 1, b] = r21 * u + r22 * v + r23 * w
            out[j, 2, b] = r31 * u + r32 * v + r33 * w
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
        rot = rotation(pose[3], pose[4], pose[5])
        sf, cf, st, ct = rot[9], rot[10], rot[11], rot[12]
        for i in range(6):
            out[b, i] = pose[i]
        for j in range(3):
            out[b, 6 + j] = rot[j] * d[0] + rot[3 + j] * d[1] + rot[6 + j] * d[2]
        out[b, 9] = d[3] - st * d[5]
        out[b, 10] = cf * d[4] + sf * ct * d[5]
        out[b, 11] = -sf * d[4] + cf * ct * d[5]
