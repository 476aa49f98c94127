"""Parametric blimp prediction model: the rigid-body ODE of paper eq. (30).

Written from the paper's Sect. 6.1.2 description (not from any simulator):

``d/dt [p, xi, v, w] = [R(xi) v, H(xi) w, M^-1 (sum F - w x M v), J^-1 (sum T - w x J w)]``

with diagonal mass ``M = diag(m1, m2, m3)`` and inertia ``J = diag(j1, j_lat,
j_lat)`` (an axisymmetric envelope), linear drag and no lift. Forces: main-fan thrust
``k_T u0`` along ``(cos(k_mu u1), 0, sin(k_mu u1))``, tail-fan side force ``k_t u2``,
net buoyancy along world z. Torques: restoring ``W h`` from the centre of gravity below the
centre of buoyancy, fan thrust at ``fan_arm`` below the centre, tail force at ``tail_arm``
behind it, linear rotational drag. ``m1`` (weighed) and ``tail_arm`` (measured) fix the
scales; the other 16 parameters are learned by least squares on one-step predictions of
recorded trajectories (paper: "16 parameters ... learned by minimizing point-wise squared
differences between simulated states and ground truth"). Noise variance is the mean
squared one-step residual. Jacobians use the complex step (exact to rounding).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from estimator_service.angles import wrap_angle
from estimator_service.models.base import ModelOutput, controls_for
from estimator_service.models.rotation import euler_rows
from estimator_service.reprs import short_repr

__all__ = ["PARAM_NAMES", "BlimpODE", "fit_blimp_ode"]

FloatArray = NDArray[np.float64]
PARAM_NAMES = (
    "m2", "m3", "j1", "j_lat", "d1", "d2", "d3", "e1", "e2", "e3",
    "net_lift", "righting", "k_thrust", "k_angle", "k_tail", "fan_arm",
)  # fmt: skip
DEFAULT_PARAMS = np.array(
    [0.6, 0.6, 0.02, 0.1, 0.05, 0.2, 0.2, 0.01, 0.04, 0.04, 0.0, 0.3, 0.15, 1.5, 0.04, 0.4]
)
_SIGNED = {"net_lift"}  # may be negative; every other parameter is positive


def _derivative(s: FloatArray, u: FloatArray, th: FloatArray, fixed: tuple[float, float]) -> FloatArray:
    """``ds/dt`` for states ``s (12, N)`` and controls ``u (3, N)`` (real or complex)."""
    m2, m3, j1, j_lat, d1, d2, d3, e1, e2, e3, lift, right, k_t, k_mu, k_tl, l_f = th
    m1, l_t = fixed
    v1, v2, v3, p, q, r = s[6], s[7], s[8], s[9], s[10], s[11]
    sin, cos = np.sin(s[3:6]), np.cos(s[3:6])  # one call each: tiny arrays
    rot = euler_rows(sin, cos)
    (sf, st, _), (cf, ct, _) = sin, cos
    thrust, mu, tail = k_t * u[0], k_mu * u[1], k_tl * u[2]
    fx, fz = thrust * np.cos(mu), thrust * np.sin(mu)
    force = (
        fx - d1 * v1 + lift * rot[2][0],
        tail - d2 * v2 + lift * rot[2][1],
        fz - d3 * v3 + lift * rot[2][2],
    )
    torque = (
        -right * rot[2][1] - e1 * p,
        right * rot[2][0] - l_f * fx - e2 * q,
        -l_t * tail - e3 * r,
    )
    mass, inertia = (m1, m2, m3), (j1, j_lat, j_lat)
    mv = (mass[0] * v1, mass[1] * v2, mass[2] * v3)
    jw = (inertia[0] * p, inertia[1] * q, inertia[2] * r)
    tq = (q * sf + r * cf) / ct
    return np.stack([
        rot[0][0] * v1 + rot[0][1] * v2 + rot[0][2] * v3,
        rot[1][0] * v1 + rot[1][1] * v2 + rot[1][2] * v3,
        rot[2][0] * v1 + rot[2][1] * v2 + rot[2][2] * v3,
        p + st * tq,
        q * cf - r * sf,
        tq,
        (force[0] - (q * mv[2] - r * mv[1])) / mass[0],
        (force[1] - (r * mv[0] - p * mv[2])) / mass[1],
        (force[2] - (p * mv[1] - q * mv[0])) / mass[2],
        (torque[0] - (q * jw[2] - r * jw[1])) / inertia[0],
        (torque[1] - (r * jw[0] - p * jw[2])) / inertia[1],
        (torque[2] - (p * jw[1] - q * jw[0])) / inertia[2],
    ])  # fmt: skip


def _change(nxt: FloatArray, x: FloatArray) -> FloatArray:
    """The state change ``nxt - x (N, 12)`` with the angle changes wrapped."""
    d = nxt - x
    d[:, 3:6] = wrap_angle(d[:, 3:6])
    return d


def integrate(
    x: FloatArray, u: FloatArray, th: FloatArray, fixed: tuple[float, float], dt: float, n_sub: int
) -> FloatArray:
    """RK4 over ``dt`` with ``u`` held: states ``x (N, 12)`` -> ``(N, 12)`` (angles wrapped)."""
    s, uu, h = x.T, u.T, dt / n_sub
    for _ in range(n_sub):
        k1 = _derivative(s, uu, th, fixed)
        k2 = _derivative(s + 0.5 * h * k1, uu, th, fixed)
        k3 = _derivative(s + 0.5 * h * k2, uu, th, fixed)
        k4 = _derivative(s + h * k3, uu, th, fixed)
        s = s + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
    return s.T


@dataclass(frozen=True)
class BlimpODE:
    """The fitted parametric prediction model (implements :class:`PredictionModel`).

    Attributes
    ----------
    params: (16,)
        Values in :data:`PARAM_NAMES` order.
    noise_var: (12,)
        Mean squared one-step residual per state dimension.
    mass, tail_arm
        Measured, not learned: the weighed mass along the body axis ``m1`` (kg) and the
        tail fan's distance behind the centre (m). They fix the scales that one-step data
        cannot (forces vs masses, torques vs inertias).
    """

    __repr__ = short_repr

    params: FloatArray
    noise_var: FloatArray
    mass: float = 0.44
    tail_arm: float = 0.8
    dt: float = 0.25
    substeps: int = 2
    state_dim: int = 12
    control_dim: int = 3
    angle_dims: tuple[int, ...] = field(default=(3, 4, 5))

    def change(self, x: FloatArray, u: FloatArray) -> FloatArray:
        """Mean state change ``(M, 12)`` (angles wrapped) over one step."""
        return _change(integrate(x, u, self.params, (self.mass, self.tail_arm), self.dt, self.substeps), x)

    def predict(self, x: FloatArray, u: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        uu = controls_for(u, x.shape[0])
        if jac:
            mean, j = self._complex_step(x, uu)
        else:
            mean, j = self.change(x, uu), None
        return ModelOutput(mean, np.broadcast_to(self.noise_var, mean.shape), j)

    def _complex_step(self, x: FloatArray, u: FloatArray, h: float = 1e-20) -> tuple[FloatArray, FloatArray]:
        """The mean change ``(M, 12)`` and ``d change / dx`` ``(M, 12, 12)`` by the complex
        step, all columns in one batch. The mean is the first column's real part: a step of
        ``1e-20 i`` changes it by ``O(h^2)``, far below rounding, so it equals :meth:`change`
        to rounding while the real-only integration is saved."""
        m, n = x.shape
        xc = np.repeat(x[:, None, :], n, axis=1).astype(np.complex128)
        xc[:, np.arange(n), np.arange(n)] += 1j * h
        uc = np.repeat(u[:, None, :], n, axis=1).reshape(m * n, -1)  # real: promoted with the state
        fixed = (self.mass, self.tail_arm)
        nxt = integrate(xc.reshape(m * n, n), uc, self.params, fixed, self.dt, self.substeps)
        nxt = nxt.reshape(m, n, n)  # [row, input j, output i]
        return _change(nxt[:, 0].real, x), nxt.imag.transpose(0, 2, 1) / h - np.eye(n)


def fit_blimp_ode(
    x: FloatArray,
    u: FloatArray,
    x_next: FloatArray,
    *,
    mass: float = 0.44,
    tail_arm: float = 0.8,
    dt: float = 0.25,
    initial: FloatArray | None = None,
    max_nfev: int = 200,
) -> BlimpODE:
    """Least-squares fit of the 16 parameters to transitions ``x (N, 12) -> x_next`` under ``u``.

    Residuals are the one-step prediction errors, each state dimension divided by its
    standard deviation of change so that all dimensions count. Positive parameters are
    fitted in log space.
    """
    x, u, x_next = (np.asarray(a, dtype=np.float64) for a in (x, u, x_next))
    if x.ndim != 2 or x.shape[1] != 12 or u.shape != (len(x), 3) or x_next.shape != x.shape:
        raise ValueError(
            f"need x (N, 12), u (N, 3), x_next (N, 12); got {x.shape}, {u.shape}, {x_next.shape}"
        )
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(u)) and np.all(np.isfinite(x_next))):
        raise ValueError("training trajectories contain NaN or Inf")
    target = x_next - x
    target[:, 3:6] = wrap_angle(target[:, 3:6])
    scale = np.maximum(target.std(axis=0), 1e-9)
    signed = np.array([n in _SIGNED for n in PARAM_NAMES])
    start = DEFAULT_PARAMS if initial is None else np.asarray(initial, dtype=np.float64)

    def unpack(z: FloatArray) -> FloatArray:
        return np.where(signed, z, np.exp(z))

    def residual(z: FloatArray) -> FloatArray:
        model = BlimpODE(unpack(z), np.ones(12), mass, tail_arm, dt)
        return ((model.change(x, u) - target) / scale).ravel()

    z0 = np.where(signed, start, np.log(np.maximum(np.abs(start), 1e-6)))
    res = least_squares(residual, z0, method="trf", x_scale="jac", max_nfev=max_nfev)
    params = unpack(res.x)
    err = BlimpODE(params, np.ones(12), mass, tail_arm, dt).change(x, u) - target
    return BlimpODE(params, np.mean(err * err, axis=0) + 1e-12, mass, tail_arm, dt)
