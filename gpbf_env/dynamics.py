"""Six-degree-of-freedom blimp dynamics: one compiled kernel for one blimp or a batch.

The ODE and its fixed-step RK4 integration are scalar code compiled by numba
(:func:`rk4_batch` loops over the blimps), so the single env and the batched vector env
run the same operations in the same order, with no per-operation array overhead.
:func:`rk4_step` and :func:`derivative` are the Python entry points.

State (12): ``x y z`` (world, m), ``phi theta psi`` (rad), ``u v w`` (body, m/s),
``p q r`` (body, rad/s). Motor state (3): main thrust (N), vector angle (rad), tail
thrust (N); each follows its command with a first-order lag that is integrated exactly
(the command is held over an env step), which keeps the RK4 integration non-stiff.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpbf_env import coeffs as C
from gpbf_env.coeffs import Coeffs, make_coeffs
from gpbf_env.jit import kernel
from gpbf_env.lab_dynamics import inflow_loss, lab_rates, motor_track, thrust_targets

__all__ = ["Coeffs", "derivative", "make_coeffs", "rk4_step", "rotation", "wrap_angle"]

FloatArray = NDArray[np.float64]
_TWO_PI = 2.0 * math.pi


@kernel
def wrap_angle(a: Any) -> Any:
    """Angles (a float or an array) wrapped to ``[-pi, pi)``."""
    return a - _TWO_PI * np.floor((a + math.pi) / _TWO_PI)


@kernel
def rotation(phi: float, th: float, psi: float) -> tuple[float, ...]:
    """Body-to-world rotation ``Rz(psi) Ry(th) Rx(phi)`` row by row ``(r11, r12, ..., r33)``,
    then ``(sin, cos)`` of roll and pitch."""
    sf, cf = math.sin(phi), math.cos(phi)
    st, ct = math.sin(th), math.cos(th)
    sp, cp = math.sin(psi), math.cos(psi)
    return (
        cp * ct, cp * st * sf - sp * cf, cp * st * cf + sp * sf,
        sp * ct, sp * st * sf + cp * cf, sp * st * cf - cp * sf,
        -st, ct * sf, ct * cf, sf, cf, st, ct,
    )  # fmt: skip


@kernel
def _derivative(
    s: FloatArray, mot: FloatArray, wind: FloatArray, k: FloatArray, lab: bool, out: FloatArray
) -> None:
    """Time derivative ``out`` (12,) of state ``s`` (12,); paper eq. (30) plus drag, lift, gusts."""
    phi, th, psi, u, v, w, p, q, r = s[3], s[4], s[5], s[6], s[7], s[8], s[9], s[10], s[11]
    r11, r12, r13, r21, r22, r23, r31, r32, r33, sf, cf, st, ct = rotation(phi, th, psi)
    wx, wy, wz = wind[0], wind[1], wind[2]
    ur = u - (r11 * wx + r21 * wy + r31 * wz)
    vr = v - (r12 * wx + r22 * wy + r32 * wz)
    wr = w - (r13 * wx + r23 * wy + r33 * wz)
    thrust, mu, tail = mot[0], mot[1], mot[2]
    if lab:
        thrust, tail = inflow_loss(thrust, mu, tail, (ur, vr, wr), (p, q, r), k)
    fx_fan, fz_fan = thrust * math.cos(mu), thrust * math.sin(mu)
    net_lift, righting = k[C.NET_LIFT], k[C.RIGHTING]
    fx = net_lift * r31 + fx_fan - (k[C.D1] + k[C.D2] * abs(ur)) * ur
    fy = net_lift * r32 + tail - (k[C.D1 + 1] + k[C.D2 + 1] * abs(vr)) * vr + k[C.Y_UV] * ur * vr
    fz = net_lift * r33 + fz_fan - (k[C.D1 + 2] + k[C.D2 + 2] * abs(wr)) * wr + k[C.Z_UW] * ur * wr
    tx = -righting * r32 - (k[C.E1] + k[C.E2] * abs(p)) * p
    ty = righting * r31 - k[C.FAN_OFFSET] * fx_fan - (k[C.E1 + 1] + k[C.E2 + 1] * abs(q)) * q
    ty = ty + k[C.M_UW] * ur * wr
    tz = -k[C.TAIL_ARM] * tail - (k[C.E1 + 2] + k[C.E2 + 2] * abs(r)) * r + k[C.N_UV] * ur * vr
    tq = (q * sf + r * cf) / ct
    out[0] = r11 * u + r12 * v + r13 * w
    out[1] = r21 * u + r22 * v + r23 * w
    out[2] = r31 * u + r32 * v + r33 * w
    out[3] = p + st * tq
    out[4] = q * cf - r * sf
    out[5] = tq
    if lab:
        lab_rates(s, (fx, fy, fz, tx, ty, tz), fx_fan, tail, r31, r33, k, out)
        return
    m1, m2, m3, j1, j2, j3 = k[C.M1], k[C.M2], k[C.M3], k[C.J1], k[C.J2], k[C.J3]
    out[6] = (fx - (q * m3 * w - r * m2 * v)) / m1
    out[7] = (fy - (r * m1 * u - p * m3 * w)) / m2
    out[8] = (fz - (p * m2 * v - q * m1 * u)) / m3
    out[9] = (tx - (q * j3 * r - r * j2 * q)) / j1
    out[10] = (ty - (r * j1 * p - p * j3 * r)) / j2
    out[11] = (tz - (p * j2 * q - q * j1 * p)) / j3


@kernel
def _motor_states(
    m0: FloatArray, cmd: FloatArray, decay: FloatArray, decay_up: FloatArray, half_times: FloatArray,
    k: FloatArray, lab: bool, track: FloatArray,
) -> None:  # fmt: skip
    """Motor states ``track`` (2 n_sub + 1, 3) over an env step with ``cmd`` held."""
    if lab:
        motor_track(m0, thrust_targets(cmd[0], cmd[1], cmd[2], k), decay, decay_up, half_times, k, track)
        return
    for j in range(track.shape[0]):
        for i in range(3):
            track[j, i] = cmd[i] + (m0[i] - cmd[i]) * decay[j, i]


@kernel
def _rk4_one(
    s: FloatArray, track: FloatArray, wind: FloatArray, k: FloatArray, lab: bool, h: float, n_sub: int,
    knots: FloatArray, b: int, scratch: FloatArray,
) -> None:  # fmt: skip
    """Integrate state ``s`` (12,) of blimp ``b`` over one env step in place (``scratch``:
    (5, 12) work space)."""
    k1, k2, k3, k4, tmp = scratch[0], scratch[1], scratch[2], scratch[3], scratch[4]
    for i in range(12):
        knots[0, i, b] = s[i]
    for j in range(n_sub):
        _derivative(s, track[2 * j], wind, k, lab, k1)
        for i in range(12):
            tmp[i] = s[i] + 0.5 * h * k1[i]
        _derivative(tmp, track[2 * j + 1], wind, k, lab, k2)
        for i in range(12):
            tmp[i] = s[i] + 0.5 * h * k2[i]
        _derivative(tmp, track[2 * j + 1], wind, k, lab, k3)
        for i in range(12):
            tmp[i] = s[i] + h * k3[i]
        _derivative(tmp, track[2 * j + 2], wind, k, lab, k4)
        for i in range(12):
            s[i] = s[i] + (h / 6.0) * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
            knots[j + 1, i, b] = s[i]


@kernel
def rk4_batch(
    state: FloatArray, motors: FloatArray, command: FloatArray, wind: FloatArray, table: FloatArray,
    decay: FloatArray, decay_up: FloatArray, half_times: FloatArray, h: float, lab: bool, knots: FloatArray,
) -> None:  # fmt: skip
    """Advance ``N`` blimps one env step in place: state (12, N), motors (3, N).

    ``command`` and ``wind`` (3, N) are held over the step; ``knots``
    (n_sub + 1, 12, N) receives the states at the start and after every sub-step
    (angles not yet wrapped). The other arguments are the fields of :class:`Coeffs`.
    """
    n_sub = knots.shape[0] - 1
    s, m0, cmd, gust = np.empty(12), np.empty(3), np.empty(3), np.empty(3)
    track, scratch = np.empty((half_times.shape[0], 3)), np.empty((5, 12))
    for b in range(state.shape[1]):
        for i in range(12):
            s[i] = state[i, b]
        for i in range(3):
            m0[i], cmd[i], gust[i] = motors[i, b], command[i, b], wind[i, b]
        k = table[b]
        _motor_states(m0, cmd, decay[b], decay_up[b], half_times, k, lab, track)
        _rk4_one(s, track, gust, k, lab, h, n_sub, knots, b, scratch)
        for i in range(12):
            state[i, b] = s[i]
        for i in (3, 4, 5):
            state[i, b] = wrap_angle(s[i])
        for i in range(3):
            motors[i, b] = track[-1, i]


def rk4_step(
    state: FloatArray, motors: FloatArray, command: FloatArray, wind: FloatArray, c: Coeffs
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Advance ``N`` blimps one env step with ``c.n_sub`` fixed RK4 sub-steps.

    Parameters
    ----------
    state: (12, N)
    motors: (3, N)
        Motor states at the start of the step.
    command: (3, N)
        Saturated motor commands, held over the step.
    wind: (3, N)
        World-frame gust velocity, held over the step.
    c
        Constants from :func:`make_coeffs` (N blimps).

    Returns
    -------
    state: (12, N)
        The state at the end of the step, angles wrapped.
    motors: (3, N)
    knots: (n_sub + 1, 12, N)
        The state at the start and after every sub-step (angles not yet wrapped).
    """
    n = c.table.shape[0]
    out = _columns(state, 12, n, "state").copy()
    mot = _columns(motors, 3, n, "motors").copy()
    cmd, gust = _columns(command, 3, n, "command"), _columns(wind, 3, n, "wind")
    knots = np.empty((c.n_sub + 1, 12, n))
    rk4_batch(out, mot, cmd, gust, c.table, c.decay, c.decay_up, c.half_times, c.h, c.lab, knots)
    return out, mot, knots


def _columns(value: object, rows: int, n: int, name: str) -> FloatArray:
    """``value`` as a contiguous ``(rows, n)`` float array (``(rows,)`` for one blimp), else
    a ValueError naming ``name``."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (rows, n) and not (n == 1 and arr.shape == (rows,)):
        raise ValueError(f"{name} must have shape ({rows}, {n}), got {arr.shape}")
    return np.ascontiguousarray(arr.reshape(rows, n))


def derivative(state: FloatArray, motors: FloatArray, wind: FloatArray, c: Coeffs) -> FloatArray:
    """Time derivative (12,) of one blimp's state (12,) under motor states and wind (3,)."""
    if c.table.shape[0] != 1:
        raise ValueError(f"derivative takes the constants of one blimp, got {c.table.shape[0]}")
    out = np.empty(12)
    s, m, w = (
        _columns(v, k, 1, name)[:, 0]
        for v, k, name in ((state, 12, "state"), (motors, 3, "motors"), (wind, 3, "wind"))
    )
    _derivative(s, m, w, c.table[0], c.lab, out)
    return out
