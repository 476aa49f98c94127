"""Checks that training can succeed, run in seconds before any expensive work.

:func:`preflight` raises :class:`PreflightError` naming the log, row, sensor or fold at
fault and the fix, and returns warnings for what is suspect but trainable:

- **time**: rows within an episode must be ``dt`` apart (5 % tolerance);
- **units**: an angle (a state component or sensor output with a period) must lie within
  half its period of 0 (degrees where radians are expected show up here);
- **data per sensor**: every observation part (a sensor, or a sensor type shared by
  several) needs :data:`MIN_READINGS` readings in the logs, and in what every calibration
  fold leaves for training;
- **rates** (warning): a sensor delivering at under half or over twice its declared
  ``rate_hz``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from estimator_service.crossfit import Fold
from estimator_service.factory import observation_parts
from estimator_service.flight import Flight
from estimator_service.system import System

__all__ = ["MIN_READINGS", "PreflightError", "PreflightWarning", "preflight"]

#: readings an observation model needs at least (a GP's hyperparameters need a few more than 2)
MIN_READINGS = 5
_DT_TOLERANCE = 0.05


class PreflightError(ValueError):
    """Training would fail or learn from wrong data; the message says where and the fix."""


class PreflightWarning(UserWarning):
    """Suspect but trainable data (e.g. a sensor's rate far from its description's)."""


def preflight(flights: Sequence[Flight], system: System, folds: Sequence[Fold]) -> list[str]:
    """Check ``flights`` (of ``system``) and the calibration ``folds`` before training;
    returns warnings, raises :class:`PreflightError` on the first fault."""
    for i, f in enumerate(flights):
        _check_times(i, f)
        _check_angles(i, f, system)
    parts = observation_parts(system)
    for part, sensors in parts.items():
        n = sum(_count(f, sensors) for f in flights)
        if n < MIN_READINGS:
            raise PreflightError(
                f"{_describe(system, part, sensors)} has {n} reading(s) in the logs; its model needs at "
                f"least {MIN_READINGS}: record longer, or give sensors of one kind a shared sensor type"
            )
    for j, fold in enumerate(folds):
        rest = fold.rest(flights)
        for part, sensors in parts.items():
            n = sum(_count(f, sensors) for f in rest)
            if n < MIN_READINGS:
                held = _count(
                    flights[fold.flight].select(np.arange(len(flights[fold.flight]))[fold.rows]), sensors
                )
                raise PreflightError(
                    f"calibration fold {j + 1} of {len(folds)} (rows {fold.rows.start}-{fold.rows.stop - 1} "
                    f"of log {fold.flight}) leaves {_describe(system, part, sensors)} {n} training "
                    f"reading(s) ({held} fall in the fold; at least {MIN_READINGS} needed): use shorter "
                    "--calibration-seconds, other --calibration-folds, or --calibration-seconds 0"
                )
    return [w for i, f in enumerate(flights) for w in _rate_warnings(i, f, system)]


def _describe(system: System, part: str, sensors: tuple[int, ...]) -> str:
    names = [system.sensors[k].name for k in sensors]
    if len(names) == 1:
        return f"sensor {names[0]!r}"
    return f"sensor type {system.sensors[sensors[0]].type!r} (sensors {', '.join(names)})"


def _count(flight: Flight, sensors: tuple[int, ...]) -> int:
    n = int(flight.valid[:, list(sensors)].sum())
    if flight.extra is not None:
        n += int(flight.extra.valid[:, list(sensors)].sum())
    return n


def _check_times(i: int, f: Flight) -> None:
    same = f.episode[1:] == f.episode[:-1]
    step = np.diff(f.t)
    bad = np.flatnonzero(same & (np.abs(step - f.dt) > _DT_TOLERANCE * f.dt))
    if bad.size:
        r = int(bad[0])
        raise PreflightError(
            f"log {i}: rows {r} and {r + 1} (t = {f.t[r]:.6g}, {f.t[r + 1]:.6g}) are {step[r]:.6g} s apart "
            f"within one episode, the description's dt is {f.dt:.6g} s ({bad.size} such gap(s)): resample "
            "to dt, start a new episode at a gap, or give the log as events (--events) to be aligned"
        )


def _check_angles(i: int, f: Flight, system: System) -> None:
    checks = [
        ("state", n, f.state[:, j], p)
        for j, (n, p) in enumerate(zip(system.state, system.state_periods, strict=True))
    ]
    for k, sensor in enumerate(system.sensors):
        rows = f.valid[:, k]
        sl = system.sensor_slice(k)
        for j, (out, p) in enumerate(zip(sensor.outputs, sensor.periods, strict=True)):
            checks.append((f"sensor {sensor.name!r} output", out, f.z[rows, sl.start + j], p))
    for what, name, values, period in checks:
        if period > 0 and values.size and np.max(np.abs(values)) > 0.5 * period * (1 + 1e-6):
            raise PreflightError(
                f"log {i}: {what} {name!r} reaches {np.max(np.abs(values)):.6g}, beyond half its period "
                f"{period:.6g}: angles must be wrapped to [-{period / 2:.6g}, {period / 2:.6g}) in the "
                "description's units (radians for a period of 2 pi; degrees given?)"
            )


def _rate_warnings(i: int, f: Flight, system: System) -> list[str]:
    seconds = len(f) * f.dt
    out = []
    for k, sensor in enumerate(system.sensors):
        if sensor.rate_hz is None or seconds <= 0:
            continue
        rate = _count(f, (k,)) / seconds
        if not 0.5 * sensor.rate_hz <= rate <= 2.0 * sensor.rate_hz:
            out.append(
                f"log {i}: sensor {sensor.name!r} delivered {rate:.3g} readings/s, its description says "
                f"{sensor.rate_hz:.3g}"
            )
    return out
