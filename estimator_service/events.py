"""Asynchronous robot logs: timestamped events aligned to the filter's steps.

A real robot's log is not one row per filter step: ground truth comes at its own rate
(motion capture at 60-120 Hz), commands at theirs (100 Hz odometry), and each sensor
delivers readings whenever it sees something, sometimes twice within one step. An
:class:`EventLog` holds these streams as recorded; :func:`align` turns it into a
:class:`~estimator_service.flight.Flight` (one row per step ``dt``) by one rule:

Alignment rule
--------------
- **Steps.** Row ``k`` is at ``t_k = start + k dt``. ``start`` defaults to the first time
  at which both the ground truth and a command (after its delay) exist; rows run to the
  last ground-truth time.
- **Ground truth** at ``t_k`` is interpolated linearly between the two samples around it
  (angle components on their circle). A gap longer than ``max_gap`` between two samples
  drops the rows inside it; the rows after it start a new episode.
- **Controls.** A command sent at time ``s`` acts from ``s + control_delay`` (the
  description's ``control_delay`` unless the call gives one). The control
  of row ``k`` (applied from ``t_k`` to ``t_{k+1}``) is, with ``control="mean"``, the
  mean of the commands acting within ``[t_k, t_{k+1})``, or the last command acting before
  ``t_k`` when none does (held); with ``control="hold"``, the last command acting at or
  before ``t_k``.
- **Readings** go to the row whose time is nearest their own (at most ``dt / 2`` away; a
  reading half-way between two rows goes to the later); readings outside the rows, or in
  rows dropped for a gap, are dropped. A sensor's first reading in a row fills the row;
  its later ones in that row are kept as extra readings
  (:class:`~estimator_service.flight.ExtraReadings`), which the filters apply after the
  row's first readings, one update each, in time order, and training uses like any other.

Readers: :func:`load_event_csv` (one event per line: ``t, stream, values...``) and
:func:`load_rosbag` (rosbag1, rosbag2 and MCAP through the ``rosbags`` package, with a
JSON topic mapping; install ``gpbf[ros]``).
"""

from __future__ import annotations

import csv
import gzip
import math
import os
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from estimator_service.flight import ExtraReadings, Flight, FlightError, make_flight
from estimator_service.system import System

__all__ = [
    "CONTROL",
    "STATE",
    "AlignReport",
    "EventLog",
    "Stream",
    "align",
    "load_event_csv",
]

FloatArray = NDArray[np.float64]
#: the stream names of the ground truth and the commands in event logs and topic mappings
STATE, CONTROL = "state", "control"
ControlRule = Literal["mean", "hold"]


@dataclass(frozen=True)
class Stream:
    """Timestamped samples: ``t (N,)`` seconds (non-decreasing), ``values (N, d)``."""

    t: FloatArray
    values: FloatArray

    @classmethod
    def of(cls, t, values, width: int, name: str) -> Stream:
        """A checked stream; :class:`FlightError` names ``name`` and the problem."""
        try:
            t = np.asarray(t, dtype=np.float64).reshape(-1)
            v = np.asarray(values, dtype=np.float64).reshape(len(t), -1) if len(t) else np.zeros((0, width))
        except (TypeError, ValueError) as exc:
            raise FlightError(
                f"stream {name!r}: times (N,) and values (N, {width}) of numbers expected ({exc})"
            ) from None
        if v.shape[1] != width:
            raise FlightError(f"stream {name!r}: {v.shape[1]} values per sample, expected {width}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(v))):
            raise FlightError(f"stream {name!r}: NaN or infinite times or values")
        if np.any(np.diff(t) < 0):
            order = np.argsort(t, kind="stable")
            t, v = t[order], v[order]
        return cls(t, v)

    def __len__(self) -> int:
        return len(self.t)


@dataclass(frozen=True)
class EventLog:
    """A robot's streams as recorded: ground truth, commands and each sensor's readings.

    Attributes
    ----------
    system
        The robot's description (state, controls, sensors, ``dt``).
    state: Stream (N, n)
        Ground truth (motion capture, survey).
    control: Stream (U, k)
        Commands at their own rate.
    readings: tuple of Stream, one per sensor (R_s, size_s)
        Each sensor's readings at their own times.
    """

    system: System
    state: Stream
    control: Stream
    readings: tuple[Stream, ...]

    @classmethod
    def from_streams(cls, system: System, streams: dict[str, tuple[Any, Any]]) -> EventLog:
        """From ``{name: (t, values)}`` with ``"state"``, ``"control"`` and sensor names
        (a sensor without readings may be left out); unknown names are an error."""
        known = {STATE, CONTROL, *(s.name for s in system.sensors)}
        unknown = sorted(set(streams) - known)
        if unknown:
            raise FlightError(f"event log: unknown stream(s) {unknown}; known: {sorted(known)}")
        for need in (STATE, CONTROL):
            if need not in streams:
                raise FlightError(f"event log: no {need!r} stream")
        empty = (np.zeros(0), np.zeros((0, 0)))
        return cls(
            system,
            Stream.of(*streams[STATE], system.state_dim, STATE),
            Stream.of(*streams[CONTROL], system.control_dim, CONTROL),
            tuple(Stream.of(*streams.get(s.name, empty), len(s.outputs), s.name) for s in system.sensors),
        )


@dataclass(frozen=True)
class AlignReport:
    """What :func:`align` did: rows made and dropped (ground-truth gaps), episodes, and per
    sensor the readings placed first in a row, kept as extra readings, and dropped (outside
    the rows)."""

    rows: int
    rows_dropped: int
    episodes: int
    first: dict[str, int]
    extra: dict[str, int]
    dropped: dict[str, int]


def align(
    log: EventLog, *, control: ControlRule = "mean", control_delay: float | None = None,
    start: float | None = None, max_gap: float | None = None,
) -> tuple[Flight, AlignReport]:  # fmt: skip
    """A flight of one row per step ``dt`` from ``log`` by the module's alignment rule.

    Parameters
    ----------
    control
        ``"mean"`` (commands acting within a step averaged) or ``"hold"``.
    control_delay
        Seconds from a command to its effect (>= 0; default: the description's).
    start
        Time of row 0 (default: the first time ground truth and a command exist).
    max_gap
        Longest ground-truth gap interpolated across (default ``5 dt``).
    """
    sys_ = log.system
    dt = sys_.dt
    if control_delay is None:
        control_delay = sys_.control_delay
    if control not in ("mean", "hold"):
        raise FlightError(f"align: control must be 'mean' or 'hold', got {control!r}")
    if not (math.isfinite(control_delay) and control_delay >= 0):
        raise FlightError(f"align: control_delay must be >= 0 seconds, got {control_delay!r}")
    gap = 5 * dt if max_gap is None else float(max_gap)
    if len(log.state) < 2 or len(log.control) < 1:
        raise FlightError("align: need at least 2 ground-truth samples and 1 command")
    act = log.control.t + control_delay
    t0 = max(log.state.t[0], act[0]) if start is None else float(start)
    if t0 < act[0] or t0 < log.state.t[0]:
        raise FlightError(f"align: start {t0} is before the first ground truth or (delayed) command")
    n = math.floor((log.state.t[-1] - t0) / dt + 1e-9) + 1
    if n < 2:
        raise FlightError("align: the ground truth spans less than two steps after the start")
    grid = t0 + dt * np.arange(n)
    state, keep = _interpolate(log.state, grid, sys_, gap)
    u = _controls(act, log.control.values, grid, dt, control)
    episode = np.cumsum(np.concatenate([[0], np.diff(np.flatnonzero(keep)) > 1]))
    rows = np.flatnonzero(keep)
    z, valid, extra, counts = _place_readings(log, t0, dt, rows, n)
    flight = make_flight(sys_, grid[rows], state[rows], u[rows], z, valid, episode, extra=extra)
    report = AlignReport(len(rows), n - len(rows), int(episode[-1]) + 1 if len(rows) else 0, *counts)
    return flight, report


def _interpolate(stream: Stream, grid: FloatArray, system: System, gap: float):
    """Ground truth at ``grid (K,)`` ``(K, n)`` and which rows lie within no gap."""
    t, v = stream.t, stream.values
    periods = np.asarray(system.state_periods)
    ang = periods > 0
    unwrapped = v.copy()
    unwrapped[:, ang] = np.unwrap(v[:, ang] * (2 * np.pi / periods[ang]), axis=0) * (
        periods[ang] / (2 * np.pi)
    )
    out = np.stack([np.interp(grid, t, unwrapped[:, j]) for j in range(v.shape[1])], axis=1)
    out[:, ang] = (out[:, ang] + periods[ang] / 2) % periods[ang] - periods[ang] / 2
    hi = np.clip(np.searchsorted(t, grid, side="right"), 1, len(t) - 1)
    keep = (t[hi] - t[hi - 1] <= gap) | (grid == t[hi - 1])
    return out, keep


def _controls(act: FloatArray, values: FloatArray, grid: FloatArray, dt: float, rule: str) -> FloatArray:
    """Per row, the mean of the commands acting within ``[t_k, t_k + dt)`` (``rule`` "mean";
    held when none) or the last acting at or before ``t_k`` ("hold")."""
    held = values[np.maximum(np.searchsorted(act, grid, side="right") - 1, 0)]
    if rule == "hold":
        return held
    lo = np.searchsorted(act, grid, side="left")
    hi = np.searchsorted(act, grid + dt, side="left")
    csum = np.concatenate([np.zeros((1, values.shape[1])), np.cumsum(values, axis=0)])
    count = (hi - lo)[:, None]
    held_before = values[np.maximum(lo - 1, 0)]
    return np.where(count > 0, (csum[hi] - csum[lo]) / np.maximum(count, 1), held_before)


def _place_readings(log: EventLog, t0: float, dt: float, rows: NDArray[np.intp], n: int):
    """``z (R, m)``, ``valid (R, S)``, the extra readings and the per-sensor counts."""
    sys_ = log.system
    row_of = np.full(n, -1)
    row_of[rows] = np.arange(len(rows))
    z, valid = np.zeros((len(rows), sys_.obs_dim)), np.zeros((len(rows), sys_.n_sensors), bool)
    extra_rows, extra_z, extra_valid, extra_t = [], [], [], []
    first, more, dropped = {}, {}, {}
    for s, (sensor, stream) in enumerate(zip(sys_.sensors, log.readings, strict=True)):
        k = np.floor((stream.t - t0) / dt + 0.5).astype(np.int64)
        inside = (k >= 0) & (k < n)
        inside[inside] = row_of[k[inside]] >= 0
        r, vals, ts = row_of[k[inside]], stream.values[inside], stream.t[inside]
        is_first = np.concatenate([[True], r[1:] != r[:-1]]) if len(r) else np.zeros(0, bool)
        sl = sys_.sensor_slice(s)
        z[r[is_first], sl] = vals[is_first]
        valid[r[is_first], s] = True
        later = ~is_first
        ez = np.zeros((int(later.sum()), sys_.obs_dim))
        ez[:, sl] = vals[later]
        ev = np.zeros((len(ez), sys_.n_sensors), bool)
        ev[:, s] = True
        extra_rows.append(r[later])
        extra_z.append(ez)
        extra_valid.append(ev)
        extra_t.append(ts[later])
        first[sensor.name], more[sensor.name] = int(is_first.sum()), int(later.sum())
        dropped[sensor.name] = int(len(stream) - inside.sum())
    extra = None
    if sum(more.values()):
        row, t_ = np.concatenate(extra_rows), np.concatenate(extra_t)
        order = np.lexsort((t_, row))
        extra = ExtraReadings(
            row[order].astype(np.int64), np.concatenate(extra_z)[order], np.concatenate(extra_valid)[order]
        )
    return z, valid, extra, (first, more, dropped)


def load_event_csv(path: str | os.PathLike[str], system: System) -> EventLog:
    """An event log from a CSV file, one event per line: ``t, stream, v1, v2, ...``.

    ``stream`` is ``state`` (the ground-truth state's components in the description's
    order), ``control`` (the controls) or a sensor's name (its outputs). A first line whose
    first cell is ``t`` is a header and skipped; lines may be of different lengths (trailing
    empty cells are ignored); lines starting with ``#`` are comments. A name ending in ``.gz``
    is read through gzip.
    """
    where = f"event log {os.fspath(path)!r}"
    sizes = {STATE: system.state_dim, CONTROL: system.control_dim}
    sizes.update({s.name: len(s.outputs) for s in system.sensors})
    data: dict[str, tuple[list[float], list[list[float]]]] = {}
    opener = gzip.open if os.fspath(path).endswith(".gz") else open
    with opener(path, "rt", newline="", encoding="utf-8") as fh:
        for i, row in enumerate(csv.reader(fh), 1):
            cells = [c.strip() for c in row]
            while cells and not cells[-1]:
                cells.pop()
            if not cells or cells[0].startswith("#") or (i == 1 and cells[0] == "t"):
                continue
            if len(cells) < 2 or cells[1] not in sizes:
                got = cells[1] if len(cells) > 1 else None
                raise FlightError(f"{where}: line {i}: stream {got!r} is none of {sorted(sizes)}")
            name = cells[1]
            if len(cells) - 2 != sizes[name]:
                raise FlightError(
                    f"{where}: line {i}: {name!r} takes {sizes[name]} values, got {len(cells) - 2}"
                )
            try:
                t, values = float(cells[0]), [float(c) for c in cells[2:]]
            except ValueError:
                raise FlightError(f"{where}: line {i}: not a number in {cells}") from None
            ts, vs = data.setdefault(name, ([], []))
            ts.append(t)
            vs.append(values)
    try:
        return EventLog.from_streams(system, {k: (t, v) for k, (t, v) in data.items()})
    except FlightError as exc:
        raise FlightError(f"{where}: {exc}") from None
