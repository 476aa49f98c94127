"""The unmodelled physics of the ``lab`` world (U1-U8 of :mod:`gpbf_env.params`).

Compiled scalar functions (numba) of one blimp, called from the RK4 kernel of
:mod:`gpbf_env.dynamics`; ``k`` is the blimp's row of :class:`~gpbf_env.coeffs.Coeffs`'
table. With reality strength 0 none of this runs and the world is the textbook one.

Rigid body with the centre of gravity at ``r_g = (0, y_g, z_g)`` from the centre of
buoyancy (the body origin): generalised momentum ``M nu`` with
``M = [[M_lin, -m S(r_g)], [m S(r_g), J]]`` (``S(a) b = a x b``), and Kirchhoff's
equations ``d(P)/dt = F - w x P``, ``d(H)/dt = tau - w x H - v x P_g`` where
``P_g = m w x r_g`` is the rigid part of the linear momentum that the textbook world's
explicit Munk moments do not already hold. Without drag, lift and gravity this conserves
the momentum and the kinetic energy ``nu' M nu / 2`` (tested).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from gpbf_env import coeffs as C
from gpbf_env.jit import kernel

__all__ = ["inflow_loss", "lab_rates", "motor_track", "thrust_targets"]

FloatArray = NDArray[np.float64]
_TINY = 1e-300


@kernel
def _pos(x: float) -> float:
    return max(x, 0.0)


@kernel
def _sign(x: float) -> float:
    return x / (abs(x) + _TINY)


@kernel
def _curve(cmd: float, top: float, reverse: float, k: FloatArray) -> float:
    a = cmd / top
    band = k[C.DEAD_BAND]
    reach = _pos((abs(a) - band) / (1.0 - band)) ** k[C.GAMMA]
    back = 1.0 + (reverse - 1.0 if a < 0 else 0.0)
    return _sign(a) * back * reach * top


@kernel
def thrust_targets(main: float, angle: float, tail: float, k: FloatArray) -> tuple[float, float, float]:
    """U1: the fans' steady thrust at the saturated commands (N, rad, N)."""
    return (
        _curve(main, k[C.MAX_MAIN], k[C.REV_MAIN], k),
        angle,
        _curve(tail, k[C.MAX_TAIL], k[C.REV_TAIL], k),
    )


@kernel
def motor_track(
    m0: FloatArray,
    target: tuple[float, float, float],
    decay: FloatArray,
    decay_up: FloatArray,
    half_times: FloatArray,
    k: FloatArray,
    out: FloatArray,
) -> None:
    """U8: motor states ``out`` (2 n_sub + 1, 3) at every half sub-step, target held.

    Fans follow a first-order lag, with the spin-up time constant while their thrust
    grows in magnitude and the textbook one (``decay`` (2 n_sub + 1, 3)) while it falls
    (``decay_up`` (2 n_sub + 1, 2)); the vector servo follows its lag capped at the slew
    rate, integrated exactly.
    """
    t0, t1, t2 = target
    up_main = 1.0 if (t0 * m0[0] >= 0 and abs(t0) > abs(m0[0])) else 0.0
    up_tail = 1.0 if (t2 * m0[2] >= 0 and abs(t2) > abs(m0[2])) else 0.0
    e0 = abs(t1 - m0[1])
    rate, tau = k[C.SERVO_RATE], k[C.TAU_ANGLE]
    knee = rate * tau
    t_knee = _pos(e0 - knee) / rate
    near = 0.5 * (e0 + knee - abs(e0 - knee))  # min(e0, knee)
    for j in range(half_times.shape[0]):
        t = half_times[j]
        d_main = decay[j, 0] + up_main * (decay_up[j, 0] - decay[j, 0])
        d_tail = decay[j, 2] + up_tail * (decay_up[j, 1] - decay[j, 2])
        ramp, settle = e0 - rate * t, near * math.exp(-_pos(t - t_knee) / tau)
        e = 0.5 * (ramp + settle + abs(ramp - settle))  # max(ramp, settle)
        out[j, 0] = t0 + (m0[0] - t0) * d_main
        out[j, 1] = t1 - (t1 - m0[1]) * (e / (e0 + _TINY))
        out[j, 2] = t2 + (m0[2] - t2) * d_tail


@kernel
def inflow_loss(
    thrust: float, mu: float, tail: float, air: tuple[float, float, float],
    rates: tuple[float, float, float], k: FloatArray,
) -> tuple[float, float]:  # fmt: skip
    """U2: fan thrusts reduced by the axial inflow (momentum theory).

    ``air`` is the body-frame air-relative velocity ``(u, v, w)`` and ``rates``
    ``(p, q, r)``: the fans' own velocity adds ``w x r_fan``.
    """
    ur, vr, wr = air
    p, q, r = rates
    v_main = (ur - k[C.FAN_OFFSET] * q) * math.cos(mu) + wr * math.sin(mu)
    v_tail = vr - k[C.TAIL_ARM] * r + k[C.TAIL_DROP] * p
    g = k[C.INFLOW_GAIN]
    return thrust * _pos(1.0 - _sign(thrust) * v_main * g), tail * _pos(1.0 - _sign(tail) * v_tail * g)


@kernel
def lab_rates(
    s: FloatArray, forces: tuple[float, float, float, float, float, float], fan_x: float, tail: float,
    r31: float, r33: float, k: FloatArray, out: FloatArray,
) -> None:  # fmt: skip
    """U3-U7: body accelerations ``out[6:12]`` of a lab blimp in state ``s`` (12,).

    ``forces`` are the textbook world's forces and moments ``(fx, fy, fz, tx, ty, tz)``,
    ``fan_x`` and ``tail`` the forward main-fan and tail-fan thrust after the inflow
    loss (N), ``r31`` and ``r33`` entries of the body-to-world rotation.
    """
    u, v, w, p, q, r = s[6], s[7], s[8], s[9], s[10], s[11]
    fx, fy, fz, tx, ty, tz = forces
    tx = tx + k[C.TAIL_DROP] * tail - k[C.WEIGHT_Y] * r33
    ty = ty + k[C.FIN_SLIP] * _pos(fan_x)
    tz = tz - k[C.IMBALANCE_ARM] * fan_x + k[C.WEIGHT_Y] * r31
    m1, m2, m3, j1, j2, j3 = k[C.M1], k[C.M2], k[C.M3], k[C.J1], k[C.J2], k[C.J3]
    my, mz = k[C.MY], k[C.MZ]
    cu, cv, cw = q * mz - r * my, -p * mz, p * my  # m w x r_g
    pu, pv, pw = m1 * u + cu, m2 * v + cv, m3 * w + cw
    hp, hq, hr = j1 * p + my * w - mz * v, j2 * q + mz * u, j3 * r - my * u
    rhs = (
        fx - (q * pw - r * pv),
        fy - (r * pu - p * pw),
        fz - (p * pv - q * pu),
        tx - (q * hr - r * hq) - (v * cw - w * cv),
        ty - (r * hp - p * hr) - (w * cu - u * cw),
        tz - (p * hq - q * hp) - (u * cv - v * cu),
    )
    for i in range(6):
        acc = 0.0
        for j in range(6):
            acc += k[C.MINV + 6 * i + j] * rhs[j]
        out[6 + i] = acc
