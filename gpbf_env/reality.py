"""How far the simulated world departs from the paper's parametric blimp model.

The parametric model (Ko & Fox 2009, Sect. 6.1.2) is a rigid body with linear fans. A
real micro-blimp has effects such a model leaves out; :class:`~gpbf_env.params.BlimpParams`
holds each one's magnitude (U1-U8, C1) and this module scales them all by one number, the
*reality strength*: 0 is the textbook world (bit for bit the ``clean`` preset), 1 the
``lab`` magnitudes, 2 twice as far from the textbook.

Presets
-------
``lab`` (the default)
    Every effect at strength 1 and indoor drafts: gust standard deviation 0.025 m/s
    (0.625 of the nominal 0.04 m/s). Office and lab air moves at a mean 0.05-0.15 m/s
    with a turbulence intensity of 20-30 % (the range the ISO 7730 draught model is
    fitted to), i.e. fluctuations of 0.01-0.045 m/s; 0.10 m/s x 25 % = 0.025 m/s.
``clean``
    The textbook world (strength 0) with the nominal gusts: the world before these
    effects existed, kept as an ablation.
``drafty``
    Every effect at strength 1 with the nominal 0.04 m/s gusts: a harsher scenario (a
    lab with the air conditioning blowing).

Gusts are a hidden state that no model of ``(x, u)`` can represent, so they are chosen
by the preset and not scaled by the strength: sweeping the strength changes only what a
learned model could learn.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from gpbf_env.params import BlimpParams

__all__ = ["PRESETS", "LabEffects", "Preset", "lab_effects"]


@dataclass(frozen=True)
class Preset:
    """A named world: reality strength and the scale on the nominal gust level."""

    strength: float
    draft_scale: float


PRESETS: dict[str, Preset] = {
    "lab": Preset(strength=1.0, draft_scale=0.625),
    "clean": Preset(strength=0.0, draft_scale=1.0),
    "drafty": Preset(strength=1.0, draft_scale=1.0),
}
MAX_STRENGTH = 4.0


@dataclass(frozen=True)
class LabEffects:
    """The unmodelled effects of one blimp at a given strength ``s`` (see BlimpParams).

    Attributes
    ----------
    gamma, dead_band, reverse_main, reverse_tail
        Thrust curve: exponent ``1 + s (gamma - 1)``, dead band ``s * band``, reverse
        ratios ``1 - s (1 - ratio)`` (floored at 0.05).
    inflow_gain
        ``s / V_e`` (s/m).
    imbalance_arm
        ``s * fan_imbalance * fan_half_span`` (m): yaw moment per newton of thrust.
    fin_slip
        ``s * fin_slipstream`` (m).
    z_g, y_g
        Centre of gravity in the body frame for the inertial coupling and the lateral
        trim: ``-s * cg_below_cb`` and ``s * cg_lateral`` (m).
    tail_drop
        ``s * tail_drop`` (m).
    tau_up_main, tau_up_tail
        Spin-up time constants, ``tau / (1 + s (tau / tau_spinup - 1))`` (s).
    servo_rate
        ``servo_rate / s`` (rad/s).
    latency, jitter
        ``s * camera_latency`` and ``s * camera_jitter`` (s).
    """

    gamma: float
    dead_band: float
    reverse_main: float
    reverse_tail: float
    inflow_gain: float
    imbalance_arm: float
    fin_slip: float
    z_g: float
    y_g: float
    tail_drop: float
    tau_up_main: float
    tau_up_tail: float
    servo_rate: float
    latency: float
    jitter: float


def lab_effects(p: BlimpParams, strength: float) -> LabEffects:
    """The effects of parameters ``p`` at reality strength ``strength > 0``."""
    s = check_strength(strength)
    if s == 0:
        raise ValueError("strength 0 is the clean world: it has no lab effects")

    def spinup(tau: float) -> float:
        return tau / (1.0 + s * (tau / p.tau_spinup - 1.0))

    return LabEffects(
        gamma=1.0 + s * (p.thrust_exponent - 1.0),
        dead_band=min(s * p.thrust_dead_band, 0.5),
        reverse_main=max(1.0 - s * (1.0 - p.reverse_main), 0.05),
        reverse_tail=max(1.0 - s * (1.0 - p.reverse_tail), 0.05),
        inflow_gain=s / p.inflow_speed,
        imbalance_arm=s * p.fan_imbalance * p.fan_half_span,
        fin_slip=s * p.fin_slipstream,
        z_g=-s * p.cg_below_cb,
        y_g=s * p.cg_lateral,
        tail_drop=s * p.tail_drop,
        tau_up_main=spinup(p.tau_main),
        tau_up_tail=spinup(p.tau_tail),
        servo_rate=p.servo_rate / s,
        latency=s * p.camera_latency,
        jitter=s * p.camera_jitter,
    )


def check_strength(strength: Any) -> float:
    """``strength`` as a float in ``[0, MAX_STRENGTH]``, else ``ValueError`` naming it."""
    try:
        s = float(strength)
    except (TypeError, ValueError):
        raise ValueError(f"reality_strength must be a number, got {strength!r}") from None
    if not (math.isfinite(s) and 0.0 <= s <= MAX_STRENGTH):
        raise ValueError(f"reality_strength must be in [0, {MAX_STRENGTH}], got {strength!r}")
    return s


def check_preset(name: Any) -> Preset:
    """The preset called ``name``, else ``ValueError`` listing the names."""
    if not isinstance(name, str) or name not in PRESETS:
        raise ValueError(f"reality must be one of {sorted(PRESETS)}, got {name!r}")
    return PRESETS[name]
