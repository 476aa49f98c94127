"""The unmodelled physics of the ``lab`` world (U1-U8 of :mod:`gpbf_env.params`).

Written like :mod:`gpbf_env.dynamics`: component-wise arithmetic on floats
(``xp=math``, one blimp) or ``(N,)`` arrays (``xp=numpy``, a batch), so both envs run the
same operations. With reality strength 0 none of this runs and the world is the
textbook one bit for bit.

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
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from gpbf_env.params import BlimpParams
from gpbf_env.reality import LabEffects, lab_effects

__all__ = ["LabCoeffs", "lab_rates", "make_lab_coeffs", "mass_matrix", "motor_track", "thrust_targets"]

Num = Any  # a float, or an (N,) float64 array
_TINY = 1e-300


@dataclass(frozen=True)
class LabCoeffs:
    """Per-blimp constants of the lab effects (floats or ``(N,)`` arrays)."""

    gamma: Num
    dead_band: Num
    reverse: tuple[Num, Num]  # main, tail
    max_thrust: tuple[Num, Num]  # main, tail (N)
    inflow_gain: Num
    imbalance_arm: Num
    fin_slip: Num
    tail_drop: Num
    weight_y: Num  # m g y_g (N m)
    my: Num  # m y_g (kg m)
    mz: Num  # m z_g (kg m)
    minv: tuple[tuple[tuple[int, Num], ...], ...]  # the nonzero entries of M^-1 per row
    decay_up: tuple[tuple[Num, Num], ...]  # spin-up lag factor (main, tail) per half sub-step
    servo_rate: Num
    tau_angle: Num
    half_times: tuple[float, ...]  # time of each half sub-step from the step's start (s)


def mass_matrix(p: BlimpParams, effects: LabEffects) -> np.ndarray:
    """The 6x6 generalised mass matrix ``M`` (rigid plus added) of one lab blimp."""
    m = p.mass
    y, z = effects.y_g, effects.z_g
    s = np.array([[0.0, -z, y], [z, 0.0, 0.0], [-y, 0.0, 0.0]])
    out = np.zeros((6, 6))
    out[:3, :3] = np.diag(p.total_mass)
    out[3:, 3:] = np.diag(p.total_inertia)
    out[:3, 3:] = -m * s
    out[3:, :3] = m * s
    return out


def make_lab_coeffs(
    params: Sequence[BlimpParams], strength: float, dt: float, n_sub: int, xp: Any
) -> LabCoeffs:
    """Lab constants for one (``xp=math``) or many (``xp=numpy``) blimps at ``strength > 0``."""
    effects = [lab_effects(p, strength) for p in params]
    scalar = xp is math

    def col(values: Sequence[float]) -> Num:
        return float(values[0]) if scalar else np.asarray(values, dtype=np.float64)

    def field(get: Any) -> Num:
        return col([float(get(p, e)) for p, e in zip(params, effects, strict=True)])

    inv = np.stack([np.linalg.inv(mass_matrix(p, e)) for p, e in zip(params, effects, strict=True)])
    minv = tuple(
        tuple((j, col(inv[:, i, j])) for j in range(6) if np.any(inv[:, i, j] != 0)) for i in range(6)
    )
    h = dt / n_sub
    half_times = tuple(k * h / 2 for k in range(2 * n_sub + 1))
    tau_up = (field(lambda p, e: e.tau_up_main), field(lambda p, e: e.tau_up_tail))
    return LabCoeffs(
        gamma=field(lambda p, e: e.gamma),
        dead_band=field(lambda p, e: e.dead_band),
        reverse=(field(lambda p, e: e.reverse_main), field(lambda p, e: e.reverse_tail)),
        max_thrust=(field(lambda p, e: p.max_main_thrust), field(lambda p, e: p.max_tail_thrust)),
        inflow_gain=field(lambda p, e: e.inflow_gain),
        imbalance_arm=field(lambda p, e: e.imbalance_arm),
        fin_slip=field(lambda p, e: e.fin_slip),
        tail_drop=field(lambda p, e: e.tail_drop),
        weight_y=field(lambda p, e: p.mass * p.gravity * e.y_g),
        my=field(lambda p, e: p.mass * e.y_g),
        mz=field(lambda p, e: p.mass * e.z_g),
        minv=minv,
        decay_up=tuple(tuple(xp.exp(-t / tau) for tau in tau_up) for t in half_times),  # type: ignore[misc]
        servo_rate=field(lambda p, e: e.servo_rate),
        tau_angle=field(lambda p, e: p.tau_angle),
        half_times=half_times,
    )


def _pos(x: Num) -> Num:
    return 0.5 * (x + abs(x))


def _sign(x: Num) -> Num:
    return x / (abs(x) + _TINY)


def _curve(cmd: Num, top: Num, reverse: Num, lab: LabCoeffs) -> Num:
    a = cmd / top
    reach = _pos((abs(a) - lab.dead_band) / (1.0 - lab.dead_band)) ** lab.gamma
    return _sign(a) * (1.0 + (a < 0) * (reverse - 1.0)) * reach * top


def thrust_targets(command: Sequence[Num], lab: LabCoeffs) -> tuple[Num, Num, Num]:
    """U1: the fans' steady thrust at the saturated commands (N, rad, N)."""
    main, angle, tail = command
    top_main, top_tail = lab.max_thrust
    rev_main, rev_tail = lab.reverse
    return _curve(main, top_main, rev_main, lab), angle, _curve(tail, top_tail, rev_tail, lab)


def motor_track(
    m0: Sequence[Num], target: Sequence[Num], decay: Sequence[Sequence[Num]], lab: LabCoeffs, xp: Any
) -> list[tuple[Num, Num, Num]]:
    """U8: motor states at every half sub-step of an env step, target held.

    Fans follow a first-order lag, with the spin-up time constant while their thrust
    grows in magnitude and the textbook one (``decay``) while it falls; the vector
    servo follows its lag capped at the slew rate, integrated exactly.
    """
    up = [(t * m >= 0) * (abs(t) > abs(m)) for t, m in ((target[0], m0[0]), (target[2], m0[2]))]
    e0 = abs(target[1] - m0[1])
    rate, tau = lab.servo_rate, lab.tau_angle
    knee = rate * tau
    t1 = _pos(e0 - knee) / rate
    near = 0.5 * (e0 + knee - abs(e0 - knee))  # min(e0, knee)
    out = []
    for k, t in enumerate(lab.half_times):
        d_main = decay[k][0] + up[0] * (lab.decay_up[k][0] - decay[k][0])
        d_tail = decay[k][2] + up[1] * (lab.decay_up[k][1] - decay[k][2])
        ramp, settle = e0 - rate * t, near * xp.exp(-_pos(t - t1) / tau)
        e = 0.5 * (ramp + settle + abs(ramp - settle))  # max(ramp, settle)
        out.append(
            (
                target[0] + (m0[0] - target[0]) * d_main,
                target[1] - (target[1] - m0[1]) * (e / (e0 + _TINY)),
                target[2] + (m0[2] - target[2]) * d_tail,
            )
        )
    return out


def inflow_loss(
    thrust: Num,
    mu: Num,
    tail: Num,
    air: Sequence[Num],
    rates: Sequence[Num],
    arms: Sequence[Num],
    lab: LabCoeffs,
    xp: Any,
) -> tuple[Num, Num]:
    """U2: fan thrusts reduced by the axial inflow (momentum theory).

    ``air`` is the body-frame air-relative velocity ``(u, v, w)``, ``rates`` ``(p, q, r)``
    and ``arms`` ``(fan_offset, tail_arm)``: the fans' own velocity adds ``w x r_fan``.
    """
    ur, vr, wr = air
    p, q, r = rates
    fan_offset, tail_arm = arms
    v_main = (ur - fan_offset * q) * xp.cos(mu) + wr * xp.sin(mu)
    v_tail = vr - tail_arm * r + lab.tail_drop * p
    g = lab.inflow_gain
    return thrust * _pos(1.0 - _sign(thrust) * v_main * g), tail * _pos(1.0 - _sign(tail) * v_tail * g)


def lab_rates(
    nu: Sequence[Num],
    forces: Sequence[Num],
    fan_x: Num,
    tail: Num,
    gravity_dir: tuple[Num, Num],
    c: Any,
) -> tuple[Num, Num, Num, Num, Num, Num]:
    """U3-U7: body accelerations ``(du, dv, dw, dp, dq, dr)`` of a lab blimp.

    Parameters
    ----------
    nu
        Body velocities ``(u, v, w, p, q, r)``.
    forces
        The textbook world's forces and moments ``(fx, fy, fz, tx, ty, tz)``.
    fan_x, tail
        Forward main-fan and tail-fan thrust after the inflow loss (N).
    gravity_dir
        ``(r31, r33)`` of the body-to-world rotation.
    c
        The :class:`~gpbf_env.dynamics.Coeffs`, with ``c.lab`` set.
    """
    lab: LabCoeffs = c.lab
    u, v, w, p, q, r = nu
    fx, fy, fz, tx, ty, tz = forces
    r31, r33 = gravity_dir
    tx = tx + lab.tail_drop * tail - lab.weight_y * r33
    ty = ty + lab.fin_slip * _pos(fan_x)
    tz = tz - lab.imbalance_arm * fan_x + lab.weight_y * r31
    m1, m2, m3 = c.m
    j1, j2, j3 = c.j
    my, mz = lab.my, lab.mz
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
    out = []
    for row in lab.minv:
        acc = 0.0
        for j, a in row:
            acc = acc + a * rhs[j]
        out.append(acc)
    return tuple(out)  # type: ignore[return-value]
