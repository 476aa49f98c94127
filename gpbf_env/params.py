"""Physical parameters of the simulated micro-blimp and its lab room.

Frames
------
World: x along the room's length, y across, z up (metres); origin at a floor corner.
Body: x forward (nose), y left, z up; origin at the envelope's centre of buoyancy.
Euler angles: roll ``phi``, pitch ``theta``, yaw ``psi`` with ``R = Rz(psi) Ry(theta) Rx(phi)``
mapping body vectors into the world. Positive pitch points the nose down.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

__all__ = ["BlimpParams", "randomize_params"]


@dataclass(frozen=True)
class BlimpParams:
    """Every physical constant of the "true" blimp world, in SI units.

    The defaults describe a 1.7 m long helium envelope with a gondola below it, close to
    the paper's testbed (Ko & Fox 2009, Sect. 6.1.1).

    Attributes
    ----------
    semi_length, semi_diameter
        Envelope ellipsoid semi-axes (m): ``a`` along body x, ``b`` along body y and z.
    mass
        Rigid mass of envelope, gas, gondola and fans (kg).
    buoyancy_ratio
        Buoyant force over weight; ``< 1`` means the blimp slowly sinks unpowered.
    added_mass
        Added (virtual) mass of the displaced air along body x, y, z (kg).
    inertia, added_inertia
        Rigid and added moments of inertia about body x, y, z (kg m^2).
    cg_below_cb
        Distance of the centre of gravity below the centre of buoyancy (m); gives
        the self-righting torque in roll and pitch.
    lin_drag, quad_drag
        Linear (N s/m) and quadratic (N s^2/m^2) translational drag per body axis.
    lin_rot_drag, quad_rot_drag
        Linear (N m s) and quadratic (N m s^2) rotational drag per body axis.
    lift_y_uv, lift_z_uw
        Body and fin lift: side force ``Y = lift_y_uv * u * v``, normal force
        ``Z = lift_z_uw * u * w`` (N s^2/m^2).
    moment_n_uv, moment_m_uw
        Net (Munk minus fin) yaw and pitch moments ``N = moment_n_uv * u * v`` and
        ``M = moment_m_uw * u * w`` (N s^2/m).
    max_main_thrust
        Saturation of the two gondola fans together, forward or reverse (N).
    max_vector_angle
        Saturation of the fan vector angle; positive tilts the thrust upward (rad).
    max_tail_thrust
        Saturation of the tail fan; positive pushes the tail to the left (+y) (N).
    fan_offset
        Distance of the gondola fans below the centre of buoyancy (m).
    tail_arm
        Distance of the tail fan behind the centre of buoyancy (m).
    tau_main, tau_angle, tau_tail
        First-order lag time constants of fan thrust, vector servo and tail fan (s).
    gust_std
        Stationary standard deviation of the wind gust velocity per world axis (m/s).
    gust_tau
        Correlation time of the gusts, an Ornstein-Uhlenbeck process (s).
    gravity, air_density
        Standard gravity (m/s^2) and air density (kg/m^3).

    Unmodelled effects
    ------------------
    What the paper's parametric model (rigid body, linear fans) leaves out. Each is
    switched on and scaled by the world's reality strength (:mod:`gpbf_env.reality`); the
    values below are the strength-1 ``lab`` magnitudes, fixed from physics and
    datasheet-level figures before any experiment was run (range in brackets).

    thrust_exponent, thrust_dead_band
        U1: static thrust of a fixed-pitch fan grows as ``|cmd|^gamma`` past a dead band
        of the motor driver: thrust goes as rotor speed squared and speed roughly
        linearly with duty above the stall duty, less the motor's speed droop (gamma 1.7
        [1.5-2]; dead band 0.07 of full command [0.05-0.10]).
    reverse_main, reverse_tail
        U1: reverse thrust over forward thrust at the same command: a cambered
        fixed-pitch blade run backwards (0.6 main [0.5-0.7], 0.8 tail [0.7-0.9], the
        tail fan's blade is nearly symmetric).
    inflow_speed
        U2: momentum theory, thrust falls as ``max(0, 1 - V_axial / V_e)`` with the
        axial inflow ``V_axial``; ``V_e`` is the fan's static slipstream speed,
        ``sqrt(2 T / (rho A))`` = 4 m/s for 0.08 N per 9 cm fan (m/s) [3-8].
    fan_imbalance, fan_half_span
        U3: the two gondola fans differ by 5 % [3-8] (motor and blade tolerance); they
        sit ``fan_half_span`` = 0.12 m either side of the centreline, so forward thrust
        ``T`` gives a yaw moment ``-fan_imbalance * fan_half_span * T``.
    fin_slipstream
        U4: the fans' slipstream drags on the lower fin 0.35 m below the centre of
        buoyancy; about 12 % of forward thrust acts there, a nose-down moment of
        ``fin_slipstream * max(T_x, 0)`` (m) [0.02-0.06].
    tail_drop
        U6: the tail fan sits 0.2 m [0.15-0.3] below the centreline (roll moment).
    cg_lateral
        U7: lateral offset of the centre of gravity from ballast placement (m) [0-0.01];
        a static roll trim. U5 (``cg_below_cb`` in the rigid-body mass matrix) has no
        constant of its own.
    tau_spinup
        U8: fans spin up with this time constant (s) [0.05-0.15] (motor torque) but spin
        down with ``tau_main`` / ``tau_tail`` (only air drag slows them).
    servo_rate
        U8: the vector servo's slew rate under load (rad/s) [2-6]: a geared micro servo
        at 0.35 s per 60 degrees; the first-order lag ``tau_angle`` still applies.
    camera_latency, camera_jitter
        C1: time from exposure to the ellipse reaching the estimator (s): USB frame
        transfer, background subtraction and the fit, 0.15 s [0.1-0.3] with 0.03 s
        standard deviation of jitter.
    """

    semi_length: float = 0.85
    semi_diameter: float = 0.32
    mass: float = 0.40
    buoyancy_ratio: float = 0.99
    added_mass: tuple[float, float, float] = (0.04, 0.33, 0.33)
    inertia: tuple[float, float, float] = (0.016, 0.068, 0.068)
    added_inertia: tuple[float, float, float] = (0.002, 0.030, 0.030)
    cg_below_cb: float = 0.10
    lin_drag: tuple[float, float, float] = (0.04, 0.12, 0.12)
    quad_drag: tuple[float, float, float] = (0.012, 0.25, 0.25)
    lin_rot_drag: tuple[float, float, float] = (0.010, 0.030, 0.030)
    quad_rot_drag: tuple[float, float, float] = (0.004, 0.040, 0.040)
    lift_y_uv: float = -0.20
    lift_z_uw: float = -0.20
    moment_n_uv: float = 0.06
    moment_m_uw: float = -0.06
    max_main_thrust: float = 0.16
    max_vector_angle: float = math.pi / 2
    max_tail_thrust: float = 0.04
    fan_offset: float = 0.40
    tail_arm: float = 0.80
    tau_main: float = 0.25
    tau_angle: float = 0.35
    tau_tail: float = 0.20
    gust_std: float = 0.04
    gust_tau: float = 3.0
    gravity: float = 9.81
    air_density: float = 1.2
    thrust_exponent: float = 1.7
    thrust_dead_band: float = 0.07
    reverse_main: float = 0.6
    reverse_tail: float = 0.8
    inflow_speed: float = 4.0
    fan_imbalance: float = 0.05
    fan_half_span: float = 0.12
    fin_slipstream: float = 0.04
    tail_drop: float = 0.2
    cg_lateral: float = 0.004
    tau_spinup: float = 0.10
    servo_rate: float = 3.0
    camera_latency: float = 0.15
    camera_jitter: float = 0.03

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            values = value if isinstance(value, tuple) else (value,)
            if not all(math.isfinite(float(v)) for v in values):
                raise ValueError(f"BlimpParams.{f.name} must be finite, got {value!r}")
        positive = (
            "semi_length semi_diameter mass buoyancy_ratio max_main_thrust max_tail_thrust "
            "tau_main tau_angle tau_tail gust_tau gravity thrust_exponent reverse_main "
            "reverse_tail inflow_speed tau_spinup servo_rate"
        ).split()
        for name in positive:
            if getattr(self, name) <= 0:
                raise ValueError(f"BlimpParams.{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("thrust_dead_band", "camera_latency", "camera_jitter", "fan_imbalance"):
            if not 0 <= getattr(self, name) < 0.5:
                raise ValueError(f"BlimpParams.{name} must be in [0, 0.5), got {getattr(self, name)!r}")

    @property
    def total_mass(self) -> tuple[float, float, float]:
        """Rigid plus added mass per body axis (kg)."""
        return tuple(self.mass + m for m in self.added_mass)  # type: ignore[return-value]

    @property
    def total_inertia(self) -> tuple[float, float, float]:
        """Rigid plus added inertia per body axis (kg m^2)."""
        return tuple(i + a for i, a in zip(self.inertia, self.added_inertia, strict=True))  # type: ignore[return-value]

    def to_dict(self) -> dict[str, Any]:
        """Plain-dict view (tuples become lists), e.g. for recording metadata."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}


def randomize_params(base: BlimpParams, rng: np.random.Generator, scale: float = 0.1) -> BlimpParams:
    """Domain randomisation: scale every positive coefficient by ``U(1 - scale, 1 + scale)``.

    Geometry (envelope size) and gravity are kept; buoyancy is perturbed around neutral.

    Parameters
    ----------
    base
        Nominal parameters.
    rng
        Source of randomness.
    scale
        Relative half-width of the uniform perturbation, in ``[0, 0.5]``.
    """
    if not 0.0 <= scale <= 0.5:
        raise ValueError(f"randomize scale must be in [0, 0.5], got {scale!r}")
    keep = {"semi_length", "semi_diameter", "gravity", "air_density", "max_vector_angle"}
    changes: dict[str, Any] = {}
    for f in fields(base):
        if f.name in keep:
            continue
        value = getattr(base, f.name)
        if f.name == "buoyancy_ratio":
            changes[f.name] = float(value + rng.uniform(-0.02, 0.02) * scale / 0.1)
        elif isinstance(value, tuple):
            factors = rng.uniform(1 - scale, 1 + scale, size=len(value))
            changes[f.name] = tuple(float(v * k) for v, k in zip(value, factors, strict=True))
        else:
            changes[f.name] = float(value * rng.uniform(1 - scale, 1 + scale))
    return dataclasses.replace(base, **changes)
