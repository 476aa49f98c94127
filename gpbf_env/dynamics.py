"""Six-degree-of-freedom blimp dynamics, written once for scalars and for batches.

Every function here is written component-wise with ``+ - * /``, ``abs`` and the
``sin``/``cos``/``exp``/``floor`` of a namespace ``xp``. Called with ``xp=math`` and Python
floats it steps one blimp with no array overhead (the single env); called with
``xp=numpy`` and ``(N,)`` arrays it steps ``N`` blimps in one vectorised pass (the
batched vector env). Both run the same operations in the same order.

State (12): ``x y z`` (world, m), ``phi theta psi`` (rad), ``u v w`` (body, m/s),
``p q r`` (body, rad/s). Motor state (3): main thrust (N), vector angle (rad), tail
thrust (N); each follows its command with a first-order lag that is integrated exactly
(the command is held over an env step), which keeps the RK4 integration non-stiff.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from gpbf_env.lab_dynamics import (
    LabCoeffs,
    inflow_loss,
    lab_rates,
    make_lab_coeffs,
    motor_track,
    thrust_targets,
)
from gpbf_env.params import BlimpParams

__all__ = ["Coeffs", "derivative", "make_coeffs", "rk4_step", "wrap_angle"]

Num = Any  # a float, or an (N,) float64 array


@dataclass(frozen=True)
class Coeffs:
    """Per-blimp constants derived from :class:`BlimpParams` (floats or ``(N,)`` arrays)."""

    m: tuple[Num, Num, Num]
    j: tuple[Num, Num, Num]
    net_lift: Num  # buoyancy minus weight (N)
    righting: Num  # weight times CG offset (N m)
    d1: tuple[Num, Num, Num]
    d2: tuple[Num, Num, Num]
    e1: tuple[Num, Num, Num]
    e2: tuple[Num, Num, Num]
    y_uv: Num
    z_uw: Num
    n_uv: Num
    m_uw: Num
    fan_offset: Num
    tail_arm: Num
    decay: tuple[tuple[Num, Num, Num], ...]  # motor lag factor at each half sub-step
    h: float  # RK4 sub-step (s)
    n_sub: int
    lab: LabCoeffs | None = None  # the unmodelled effects; None in the textbook world


def _stack(values: Sequence[float], xp: Any) -> Num:
    return values[0] if xp is math else np.asarray(values, dtype=np.float64)


def make_coeffs(
    params: Sequence[BlimpParams], dt: float, n_sub: int, xp: Any, strength: float = 0.0
) -> Coeffs:
    """Derive integration constants for one (``xp=math``) or many (``xp=numpy``) blimps.

    Parameters
    ----------
    params
        One parameter set per blimp; exactly one when ``xp`` is :mod:`math`.
    dt
        Env step (s); controls are held over it.
    n_sub
        RK4 sub-steps per env step.
    strength
        Reality strength of the unmodelled effects (:mod:`gpbf_env.reality`); 0 is the
        textbook world.
    """
    if xp is math and len(params) != 1:
        raise ValueError("scalar dynamics take exactly one BlimpParams")

    def col(get: Any) -> Num:
        return _stack([float(get(p)) for p in params], xp)

    def vec(get: Any) -> tuple[Num, Num, Num]:
        return tuple(col(lambda p, i=i: get(p)[i]) for i in range(3))  # type: ignore[return-value]

    h = dt / n_sub
    taus = (
        col(lambda p: p.tau_main),
        col(lambda p: p.tau_angle),
        col(lambda p: p.tau_tail),
    )
    decay = tuple(tuple(xp.exp(-(k * h / 2) / tau) for tau in taus) for k in range(2 * n_sub + 1))
    return Coeffs(
        m=vec(lambda p: p.total_mass),
        j=vec(lambda p: p.total_inertia),
        net_lift=col(lambda p: (p.buoyancy_ratio - 1.0) * p.mass * p.gravity),
        righting=col(lambda p: p.mass * p.gravity * p.cg_below_cb),
        d1=vec(lambda p: p.lin_drag),
        d2=vec(lambda p: p.quad_drag),
        e1=vec(lambda p: p.lin_rot_drag),
        e2=vec(lambda p: p.quad_rot_drag),
        y_uv=col(lambda p: p.lift_y_uv),
        z_uw=col(lambda p: p.lift_z_uw),
        n_uv=col(lambda p: p.moment_n_uv),
        m_uw=col(lambda p: p.moment_m_uw),
        fan_offset=col(lambda p: p.fan_offset),
        tail_arm=col(lambda p: p.tail_arm),
        decay=decay,
        h=h,
        n_sub=n_sub,
        lab=make_lab_coeffs(params, strength, dt, n_sub, xp) if strength > 0 else None,
    )


def wrap_angle(a: Num, xp: Any) -> Num:
    """Wrap an angle to ``[-pi, pi)``."""
    return a - 2.0 * math.pi * xp.floor((a + math.pi) / (2.0 * math.pi))


def derivative(s: Sequence[Num], mot: Sequence[Num], wind: Sequence[Num], c: Coeffs, xp: Any):
    """Time derivative of the 12-D state; paper eq. (30) plus drag, lift and gusts."""
    _, _, _, phi, th, psi, u, v, w, p, q, r = s
    sf, cf = xp.sin(phi), xp.cos(phi)
    st, ct = xp.sin(th), xp.cos(th)
    sp, cp = xp.sin(psi), xp.cos(psi)
    r11, r12, r13 = cp * ct, cp * st * sf - sp * cf, cp * st * cf + sp * sf
    r21, r22, r23 = sp * ct, sp * st * sf + cp * cf, sp * st * cf - cp * sf
    r31, r32, r33 = -st, ct * sf, ct * cf
    wx, wy, wz = wind
    ur = u - (r11 * wx + r21 * wy + r31 * wz)
    vr = v - (r12 * wx + r22 * wy + r32 * wz)
    wr = w - (r13 * wx + r23 * wy + r33 * wz)
    thrust, mu, tail = mot
    if c.lab is not None:
        thrust, tail = inflow_loss(
            thrust, mu, tail, (ur, vr, wr), (p, q, r), (c.fan_offset, c.tail_arm), c.lab, xp
        )
    fx_fan, fz_fan = thrust * xp.cos(mu), thrust * xp.sin(mu)
    d1, d2, e1, e2 = c.d1, c.d2, c.e1, c.e2
    fx = c.net_lift * r31 + fx_fan - (d1[0] + d2[0] * abs(ur)) * ur
    fy = c.net_lift * r32 + tail - (d1[1] + d2[1] * abs(vr)) * vr + c.y_uv * ur * vr
    fz = c.net_lift * r33 + fz_fan - (d1[2] + d2[2] * abs(wr)) * wr + c.z_uw * ur * wr
    tx = -c.righting * r32 - (e1[0] + e2[0] * abs(p)) * p
    ty = c.righting * r31 - c.fan_offset * fx_fan - (e1[1] + e2[1] * abs(q)) * q
    ty = ty + c.m_uw * ur * wr
    tz = -c.tail_arm * tail - (e1[2] + e2[2] * abs(r)) * r + c.n_uv * ur * vr
    m1, m2, m3 = c.m
    j1, j2, j3 = c.j
    tq = (q * sf + r * cf) / ct
    kinematics = (
        r11 * u + r12 * v + r13 * w,
        r21 * u + r22 * v + r23 * w,
        r31 * u + r32 * v + r33 * w,
        p + st * tq,
        q * cf - r * sf,
        tq,
    )
    if c.lab is not None:
        nu = (u, v, w, p, q, r)
        return (*kinematics, *lab_rates(nu, (fx, fy, fz, tx, ty, tz), fx_fan, tail, (r31, r33), c))
    return (
        *kinematics,
        (fx - (q * m3 * w - r * m2 * v)) / m1,
        (fy - (r * m1 * u - p * m3 * w)) / m2,
        (fz - (p * m2 * v - q * m1 * u)) / m3,
        (tx - (q * j3 * r - r * j2 * q)) / j1,
        (ty - (r * j1 * p - p * j3 * r)) / j2,
        (tz - (p * j2 * q - q * j1 * p)) / j3,
    )


def _motors_at(m0: Sequence[Num], cmd: Sequence[Num], k: int, c: Coeffs) -> tuple[Num, ...]:
    return tuple(ci + (mi - ci) * di for mi, ci, di in zip(m0, cmd, c.decay[k], strict=True))


def rk4_step(
    state: Sequence[Num],
    motors: Sequence[Num],
    command: Sequence[Num],
    wind: Sequence[Num],
    c: Coeffs,
    xp: Any,
    knots: list[list[Num]] | None = None,
) -> tuple[list[Num], tuple[Num, ...]]:
    """Advance one env step with ``c.n_sub`` fixed RK4 sub-steps.

    Parameters
    ----------
    state
        12 components (floats, or ``(N,)`` arrays).
    motors
        3 motor states at the start of the step.
    command
        3 saturated motor commands, held over the step.
    wind
        3 world-frame gust velocity components, held over the step.
    c
        Constants from :func:`make_coeffs`.
    xp
        :mod:`math` or :mod:`numpy`.
    knots
        When given, the state at the start and after every sub-step (``n_sub + 1``
        states, angles not yet wrapped) is appended to it.

    Returns
    -------
    state, motors
        The state (angles wrapped) and motor states at the end of the step.
    """
    s = list(state)
    h = c.h
    if c.lab is None:
        track = [_motors_at(motors, command, k, c) for k in range(2 * c.n_sub + 1)]
    else:
        track = motor_track(motors, thrust_targets(command, c.lab), c.decay, c.lab, xp)
    if knots is not None:
        knots.append(s)
    for j in range(c.n_sub):
        m_a, m_b, m_c = track[2 * j], track[2 * j + 1], track[2 * j + 2]
        k1 = derivative(s, m_a, wind, c, xp)
        k2 = derivative([a + 0.5 * h * b for a, b in zip(s, k1, strict=True)], m_b, wind, c, xp)
        k3 = derivative([a + 0.5 * h * b for a, b in zip(s, k2, strict=True)], m_b, wind, c, xp)
        k4 = derivative([a + h * b for a, b in zip(s, k3, strict=True)], m_c, wind, c, xp)
        s = [
            a + (h / 6.0) * (b1 + 2.0 * b2 + 2.0 * b3 + b4)
            for a, b1, b2, b3, b4 in zip(s, k1, k2, k3, k4, strict=True)
        ]
        if knots is not None:
            knots.append(s)
    s = list(s)
    for i in (3, 4, 5):
        s[i] = wrap_angle(s[i], xp)
    return s, track[-1]
