"""Per-blimp integration constants, packed for the compiled dynamics.

:func:`make_coeffs` turns :class:`~gpbf_env.params.BlimpParams` (and, in the lab world,
:func:`~gpbf_env.reality.lab_effects`) into one row of a float table per blimp; the
column names below are the only place the layout is written down, and
:mod:`gpbf_env.dynamics` and :mod:`gpbf_env.lab_dynamics` read the table through them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gpbf_env.params import BlimpParams
from gpbf_env.reality import LabEffects, lab_effects

__all__ = ["Coeffs", "make_coeffs", "mass_matrix"]

FloatArray = NDArray[np.float64]

# textbook world: masses and inertias with added mass, lift, drag (linear, quadratic)
M1, M2, M3, J1, J2, J3 = range(6)
NET_LIFT, RIGHTING = 6, 7  # buoyancy minus weight (N); weight times CG offset (N m)
D1, D2, E1, E2 = 8, 11, 14, 17  # three columns each: x, y, z (or roll, pitch, yaw)
Y_UV, Z_UW, N_UV, M_UW, FAN_OFFSET, TAIL_ARM = range(20, 26)
# lab world (U1-U8 of gpbf_env.params, at the preset's strength)
GAMMA, DEAD_BAND, REV_MAIN, REV_TAIL, MAX_MAIN, MAX_TAIL = range(26, 32)
INFLOW_GAIN, IMBALANCE_ARM, FIN_SLIP, TAIL_DROP = range(32, 36)
WEIGHT_Y, MY, MZ, SERVO_RATE, TAU_ANGLE = range(36, 41)  # m g y_g (N m), m y_g, m z_g (kg m)
MINV = 41  # 36 columns: the inverse 6x6 mass matrix, row by row
N_COLUMNS = MINV + 36


@dataclass(frozen=True, eq=False)  # arrays: identity, not elementwise, equality
class Coeffs:
    """Constants of ``N`` blimps for :func:`gpbf_env.dynamics.rk4_step`.

    Attributes
    ----------
    table: (N, N_COLUMNS)
        One row per blimp, columns named by this module's constants.
    decay: (N, 2 n_sub + 1, 3)
        Motor lag factor (main, angle, tail) at each half sub-step of an env step.
    decay_up: (N, 2 n_sub + 1, 2)
        Spin-up lag factor (main, tail) at each half sub-step (lab world; ones otherwise).
    half_times: (2 n_sub + 1,)
        Time of each half sub-step from the step's start (s).
    h
        RK4 sub-step (s).
    n_sub
        RK4 sub-steps per env step.
    lab
        Whether the unmodelled effects act (reality strength > 0).
    """

    table: FloatArray
    decay: FloatArray
    decay_up: FloatArray
    half_times: FloatArray
    h: float
    n_sub: int
    lab: bool


def mass_matrix(p: BlimpParams, effects: LabEffects) -> FloatArray:
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


def _textbook_row(p: BlimpParams) -> list[float]:
    return [
        *p.total_mass, *p.total_inertia,
        (p.buoyancy_ratio - 1.0) * p.mass * p.gravity, p.mass * p.gravity * p.cg_below_cb,
        *p.lin_drag, *p.quad_drag, *p.lin_rot_drag, *p.quad_rot_drag,
        p.lift_y_uv, p.lift_z_uw, p.moment_n_uv, p.moment_m_uw, p.fan_offset, p.tail_arm,
    ]  # fmt: skip


def _lab_row(p: BlimpParams, e: LabEffects) -> list[float]:
    return [
        e.gamma, e.dead_band, e.reverse_main, e.reverse_tail, p.max_main_thrust, p.max_tail_thrust,
        e.inflow_gain, e.imbalance_arm, e.fin_slip, e.tail_drop,
        p.mass * p.gravity * e.y_g, p.mass * e.y_g, p.mass * e.z_g, e.servo_rate, p.tau_angle,
        *np.linalg.inv(mass_matrix(p, e)).ravel(),
    ]  # fmt: skip


def make_coeffs(params: Sequence[BlimpParams], dt: float, n_sub: int, strength: float = 0.0) -> Coeffs:
    """Derive the integration constants of ``N`` blimps.

    Parameters
    ----------
    params
        One parameter set per blimp.
    dt
        Env step (s); controls are held over it.
    n_sub
        RK4 sub-steps per env step.
    strength
        Reality strength of the unmodelled effects (:mod:`gpbf_env.reality`); 0 is the
        textbook world.
    """
    lab = strength > 0
    effects = [lab_effects(p, strength) for p in params] if lab else []
    rows = [_textbook_row(p) for p in params]
    for row, p, e in zip(rows, params, effects or [None] * len(params), strict=True):
        row += _lab_row(p, e) if e is not None else [0.0] * (N_COLUMNS - len(row))
    table = np.asarray(rows, dtype=np.float64).reshape(len(params), N_COLUMNS)
    h = dt / n_sub
    half_times = np.arange(2 * n_sub + 1) * h / 2
    taus = np.array([[p.tau_main, p.tau_angle, p.tau_tail] for p in params])
    decay = np.exp(-half_times[None, :, None] / taus[:, None, :])
    if lab:
        tau_up = np.array([[e.tau_up_main, e.tau_up_tail] for e in effects])
        decay_up = np.exp(-half_times[None, :, None] / tau_up[:, None, :])
    else:
        decay_up = np.ones((len(params), 2 * n_sub + 1, 2))
    return Coeffs(table, decay, decay_up, half_times, h, n_sub, lab)
