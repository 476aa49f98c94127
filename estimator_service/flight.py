"""Logs of a robot's runs ("flights"): the data the estimator trains, calibrates and is scored on.

A :class:`Flight` holds, per row (one filter step ``dt`` apart within an episode):

=============  ===========  =================================================================
``t``          (N,)         time of the row (s)
``state``      (N, n)       ground-truth state (e.g. motion capture) at that time
``control``    (N, k)       control applied from this row to the next (0 on the last)
``z``          (N, m)       sensor values at this row, all sensors side by side (0 where none)
``valid``      (N, S)       whether sensor ``s`` delivered a reading at this row
``episode``    (N,)         episode index; rows of different episodes are not transitions
``metadata``   dict         JSON: ``system`` (the :class:`~estimator_service.system.System`),
                            and anything else the recorder wants to keep
``exact``      (N, n)       optional: the exact state where a simulator knows it (``state``
                            is then what its measurement system, e.g. simulated motion
                            capture, reported: what models train on, as on a real robot)
``extra``                   optional :class:`ExtraReadings`: a sensor's second and later
                            readings within one row (aligned event logs,
                            :mod:`estimator_service.events`); filters apply them after the
                            row's first readings, one update each, in time order
=============  ===========  =================================================================

On disk: one NumPy ``.npz`` (``allow_pickle=False``) with those keys and ``metadata`` as
a JSON string (format ``gpbf-flight``, version 2, ``exact`` and ``extra_row``,
``extra_z``, ``extra_valid`` stored when present;
version-1 files of the blimp simulator, which stored ``ellipses (N, C, 5)``, are
read too), written atomically. Logs from elsewhere come in as CSV (:func:`load_csv`,
layout in ``docs/your-robot.md``).
"""

from __future__ import annotations

import csv
import functools
import json
import math
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from estimator_service.files import atomic_savez, npz_oversized, npz_unreadable
from estimator_service.system import DescriptionError, System

__all__ = [
    "FLIGHT_FORMAT_VERSION",
    "ExtraReadings",
    "Flight",
    "FlightError",
    "load_csv",
    "load_flight",
    "load_log",
    "save_flight",
]

FLIGHT_FORMAT = "gpbf-flight"
FLIGHT_FORMAT_VERSION = 2
FloatArray = NDArray[np.float64]
_KEYS = ("t", "state", "control", "z", "valid", "episode")


class FlightError(ValueError):
    """A log file is unreadable or does not fit its system description."""


@dataclass(frozen=True)
class ExtraReadings:
    """Readings beyond a sensor's first within one row, in time order.

    Attributes
    ----------
    row: (E,) int
        The flight row each belongs to (non-decreasing).
    z: (E, m)
        The values, laid out as the flight's ``z`` (0 outside the sensor's outputs).
    valid: (E, S) bool
        The one sensor each reading is of.
    """

    row: NDArray[np.int64]
    z: FloatArray
    valid: NDArray[np.bool_]

    def __len__(self) -> int:
        return len(self.row)

    def take(self, keep: NDArray[np.bool_], row: NDArray[np.int64] | None = None) -> ExtraReadings | None:
        """The readings where ``keep``, with new row numbers ``row`` (all of them) if given;
        None when none is kept."""
        if not keep.any():
            return None
        rows = self.row[keep] if row is None else row[keep]
        return ExtraReadings(rows.astype(np.int64), self.z[keep], self.valid[keep])

    def at(self, row: int) -> range:
        """Indices of the readings of ``row``."""
        return range(*np.searchsorted(self.row, [row, row + 1]))


_EXTRA_KEYS = ("extra_row", "extra_z", "extra_valid")


@dataclass(frozen=True)
class Flight:
    """One recorded run (see the module docstring for the fields)."""

    t: FloatArray
    state: FloatArray
    control: FloatArray
    z: FloatArray
    valid: NDArray[np.bool_]
    episode: NDArray[np.int64]
    metadata: dict[str, Any]
    exact: FloatArray | None = None
    extra: ExtraReadings | None = None

    def __post_init__(self) -> None:
        self.check()  # also caches the parsed system description

    def __len__(self) -> int:
        return len(self.t)

    def __repr__(self) -> str:
        eps = int(self.episode.max()) + 1 if len(self) else 0
        frames = self.valid.sum(0).tolist()
        return f"Flight({self.system.name!r}, rows={len(self)}, episodes={eps}, frames={frames})"

    @functools.cached_property
    def system(self) -> System:
        return System.from_dict(self.metadata["system"], "flight metadata 'system'")

    @property
    def dt(self) -> float:
        return float(self.metadata["system"]["dt"])

    @property
    def n_sensors(self) -> int:
        return self.valid.shape[1]

    def check(self, where: str = "flight") -> None:
        """Raise :class:`FlightError` naming the field whose shape or values do not fit."""
        if "system" not in self.metadata:
            raise FlightError(f"{where}: metadata has no 'system' description")
        try:
            sys_ = self.system
        except DescriptionError as exc:
            raise FlightError(f"{where}: {exc}") from None
        if np.ndim(self.t) != 1:
            raise FlightError(f"{where}: 't' must be a 1-D array of times, got shape {np.shape(self.t)}")
        n = len(self.t)
        shapes = {
            "t": (n,), "state": (n, sys_.state_dim), "control": (n, sys_.control_dim),
            "z": (n, sys_.obs_dim), "valid": (n, sys_.n_sensors), "episode": (n,),
        }  # fmt: skip
        for key, shape in shapes.items():
            if np.shape(getattr(self, key)) != shape:
                raise FlightError(
                    f"{where}: '{key}' has shape {np.shape(getattr(self, key))}, expected {shape}"
                )
        if self.exact is not None and np.shape(self.exact) != shapes["state"]:
            raise FlightError(
                f"{where}: 'exact' has shape {np.shape(self.exact)}, expected {shapes['state']}"
            )
        for key in ("t", "state", "control", "exact"):
            values = getattr(self, key)
            if values is not None and not np.all(np.isfinite(values)):
                raise FlightError(f"{where}: '{key}' has NaN or infinite values")
        if not np.all(np.isfinite(self.z[self.expand_valid()])):
            raise FlightError(f"{where}: 'z' has NaN or infinite values where 'valid' is set")
        if n and np.any(np.diff(self.episode) < 0):
            raise FlightError(f"{where}: 'episode' must not decrease")
        if self.extra is not None:
            self._check_extra(where, sys_)

    def _check_extra(self, where: str, sys_: System) -> None:
        e = self.extra
        k = len(e.row)
        if np.shape(e.z) != (k, sys_.obs_dim) or np.shape(e.valid) != (k, sys_.n_sensors):
            raise FlightError(
                f"{where}: 'extra_z' {np.shape(e.z)} and 'extra_valid' {np.shape(e.valid)} must be "
                f"({k}, {sys_.obs_dim}) and ({k}, {sys_.n_sensors})"
            )
        if k and (e.row.min() < 0 or e.row.max() >= len(self.t) or np.any(np.diff(e.row) < 0)):
            raise FlightError(f"{where}: 'extra_row' must be non-decreasing rows of the flight")
        if k and not np.all(e.valid.sum(axis=1) == 1):
            raise FlightError(f"{where}: each extra reading must be of exactly one sensor")
        if not np.all(np.isfinite(e.z[sys_.expand_valid(e.valid)])):
            raise FlightError(f"{where}: 'extra_z' has NaN or infinite values where 'extra_valid' is set")

    def expand_valid(self) -> NDArray[np.bool_]:
        """Per-output validity ``(N, m)``."""
        return self.system.expand_valid(self.valid)

    def readings(self, sensor: int) -> tuple[FloatArray, FloatArray]:
        """States ``(T, n)`` and values ``(T, size)`` of every reading of ``sensor`` (a row's
        first, then the extra readings), each with the state of its row."""
        rows = np.flatnonzero(self.valid[:, sensor])
        z = self.z[rows]
        if self.extra is not None:
            more = self.extra.valid[:, sensor]
            rows = np.concatenate([rows, self.extra.row[more]])
            z = np.concatenate([z, self.extra.z[more]])
        return self.state[rows], z[:, self.system.sensor_slice(sensor)]

    def transition_rows(self) -> NDArray[np.intp]:
        """Rows ``k`` whose successor ``k + 1`` belongs to the same episode."""
        return np.flatnonzero(self.episode[:-1] == self.episode[1:])

    def transitions(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``x_k (T, n)``, ``u_k (T, k)``, ``x_{k+1} (T, n)`` within episodes."""
        k = self.transition_rows()
        return self.state[k], self.control[k], self.state[k + 1]

    def select(self, rows: NDArray[np.intp]) -> Flight:
        """The rows ``rows`` (sorted) as a new flight."""
        rows = np.asarray(rows, dtype=np.intp)
        exact = None if self.exact is None else self.exact[rows]
        extra = None
        if self.extra is not None and len(rows):
            at = np.minimum(np.searchsorted(rows, self.extra.row), len(rows) - 1)
            extra = self.extra.take(rows[at] == self.extra.row, at.astype(np.int64))
        return Flight(*(getattr(self, k)[rows] for k in _KEYS), self.metadata, exact, extra)

    def without_readings(self, rows: slice) -> Flight:
        """This flight with no sensor readings in ``rows`` (states, controls kept)."""
        valid = self.valid.copy()
        valid[rows] = False
        extra = self.extra
        if extra is not None:
            start, stop, _ = rows.indices(len(self))
            extra = extra.take((extra.row < start) | (extra.row >= stop))
        return replace(self, valid=valid, extra=extra)


def make_flight(
    system: System, t, state, control, z, valid, episode=None, exact=None,
    extra: ExtraReadings | None = None, **metadata: Any,
) -> Flight:  # fmt: skip
    """A :class:`Flight` from arrays (``valid`` per sensor ``(N, S)``; ``episode`` default 0;
    ``exact`` the simulator's exact states, if any; ``extra`` later readings within a row)."""
    t = np.asarray(t, dtype=np.float64)
    ep = np.zeros(len(t), np.int64) if episode is None else np.asarray(episode, dtype=np.int64)
    meta = {"format": FLIGHT_FORMAT, "version": FLIGHT_FORMAT_VERSION, **metadata, "system": system.to_dict()}
    z = np.asarray(z, dtype=np.float64)
    v = np.asarray(valid, dtype=bool)
    return Flight(
        t,
        np.asarray(state, float),
        np.asarray(control, float),
        np.where(system.expand_valid(v), z, 0.0),
        v,
        ep,
        meta,
        None if exact is None else np.asarray(exact, float),
        extra,
    )


def save_flight(flight: Flight, path: str | os.PathLike[str]) -> Path:
    """Write ``flight`` to ``path`` (``.npz``) atomically."""
    meta = {**flight.metadata, "format": FLIGHT_FORMAT, "version": FLIGHT_FORMAT_VERSION}
    arrays = {k: getattr(flight, k) for k in _KEYS}
    if flight.exact is not None:
        arrays["exact"] = flight.exact
    if flight.extra is not None:
        arrays.update(zip(_EXTRA_KEYS, (flight.extra.row, flight.extra.z, flight.extra.valid), strict=True))
    return atomic_savez(path, **arrays, metadata=np.array(json.dumps(meta)))


def load_flight(path: str | os.PathLike[str]) -> Flight:
    """Read a flight file; :class:`FlightError` names the problem for a malformed one."""
    where = f"flight file {os.fspath(path)!r}"
    try:
        with np.load(path, allow_pickle=False) as d:
            oversized = npz_oversized(d)
            data = {} if oversized else {k: d[k] for k in d.files}
    except FileNotFoundError:
        raise
    except Exception as exc:
        why = npz_unreadable(exc)
        hint = "; a CSV log needs a .csv name and a --system description" if why.startswith("not a") else ""
        raise FlightError(f"{where}: {why}{hint}") from exc
    if oversized:
        raise FlightError(f"{where}: {oversized} (a damaged or hostile file)")
    if "metadata" not in data:
        raise FlightError(f"{where}: missing 'metadata'")
    try:
        meta = json.loads(str(data["metadata"]))
    except json.JSONDecodeError as exc:
        raise FlightError(f"{where}: 'metadata' is not JSON ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != FLIGHT_FORMAT:
        raise FlightError(f"{where}: not a {FLIGHT_FORMAT} file")
    if meta.get("version") == 1:
        data, meta = _from_version_1(data, meta, where)
    elif meta.get("version") != FLIGHT_FORMAT_VERSION:
        raise FlightError(
            f"{where}: version {meta.get('version')!r}; this reads 1 and {FLIGHT_FORMAT_VERSION}"
        )
    missing = [k for k in _KEYS if k not in data]
    if missing:
        raise FlightError(f"{where}: missing {missing}")
    _check_rows(data, where)
    return Flight(
        *(np.asarray(data[k], dtype=np.float64) for k in ("t", "state", "control", "z")),
        np.asarray(data["valid"]).astype(bool),
        np.asarray(data["episode"]).astype(np.int64),
        meta,
        np.asarray(data["exact"], dtype=np.float64) if "exact" in data else None,
        _extra_from(data, where),
    )


def _check_rows(data: dict, where: str) -> None:
    """At least one row of times, and episode numbers that are whole numbers (a NaN would
    become an arbitrary integer when cast)."""
    t, episode = np.asarray(data["t"]), np.asarray(data["episode"])
    if t.ndim != 1 or len(t) == 0:
        raise FlightError(f"{where}: 't' must be a 1-D array with at least one row, got shape {t.shape}")
    if not np.issubdtype(episode.dtype, np.integer):
        whole = np.issubdtype(episode.dtype, np.floating) and np.all(
            np.isfinite(episode) & (episode % 1 == 0)
        )
        if not whole:
            raise FlightError(
                f"{where}: 'episode' must hold whole numbers, got {episode.dtype} with NaN or fractions"
            )


def _extra_from(data: dict, where: str) -> ExtraReadings | None:
    have = [k for k in _EXTRA_KEYS if k in data]
    if not have:
        return None
    if len(have) != len(_EXTRA_KEYS):
        raise FlightError(f"{where}: has {have} but not all of {list(_EXTRA_KEYS)}")
    row, z, valid = (data[k] for k in _EXTRA_KEYS)
    if row.ndim != 1 or z.ndim != 2 or valid.ndim != 2:
        raise FlightError(f"{where}: 'extra_row' must be 1-D, 'extra_z' and 'extra_valid' 2-D")
    return ExtraReadings(row.astype(np.int64), z.astype(np.float64), valid.astype(bool))


def _from_version_1(data: dict, meta: dict, where: str) -> tuple[dict, dict]:
    """A blimp-simulator flight of format version 1: ``ellipses (N, C, 5)``, no system."""
    from estimator_service.blimp import blimp_system

    ell = data.get("ellipses")
    if ell is None or ell.ndim != 3:
        raise FlightError(f"{where}: version-1 file without 'ellipses' (N, C, 5)")
    data = {**data, "z": ell.reshape(len(ell), -1)}
    return data, {
        **meta,
        "version": FLIGHT_FORMAT_VERSION,
        "system": blimp_system(ell.shape[1], meta["dt"]).to_dict(),
    }


def load_csv(path: str | os.PathLike[str], system: System) -> Flight:
    """A flight from a CSV log with a header row naming the columns.

    Columns: ``t``; one per state component and control (their names in ``system``);
    ``<sensor>.<output>`` for each sensor output, left empty (or ``nan``) at rows where
    that sensor delivered nothing; optionally ``episode``. Other columns are ignored.
    """
    where = f"CSV log {os.fspath(path)!r}"
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise FlightError(f"{where}: empty")
    header = [h.strip() for h in rows[0]]
    col = {h: i for i, h in enumerate(header)}
    outs = [f"{s.name}.{o}" for s in system.sensors for o in s.outputs]
    need = ["t", *system.state, *system.controls, *outs]
    missing = [h for h in need if h not in col]
    if missing:
        raise FlightError(f"{where}: missing column(s) {missing}")
    table = np.full((len(rows) - 1, len(header)), math.nan)
    for i, row in enumerate(rows[1:]):
        if len(row) != len(header):
            raise FlightError(f"{where}: line {i + 2} has {len(row)} fields, the header {len(header)}")
        for j, cell in enumerate(row):
            if cell.strip():
                try:
                    table[i, j] = float(cell)
                except ValueError:
                    raise FlightError(
                        f"{where}: line {i + 2}, column {header[j]!r}: not a number: {cell!r}"
                    ) from None
    pick = lambda names: table[:, [col[h] for h in names]]  # noqa: E731
    z = pick(outs)
    have = np.isfinite(z)
    valid = np.stack([have[:, system.sensor_slice(k)].all(axis=1) for k in range(system.n_sensors)], axis=1)
    partial = (
        np.stack([have[:, system.sensor_slice(k)].any(axis=1) for k in range(system.n_sensors)], axis=1)
        & ~valid
    )
    if partial.any():
        r, k = np.argwhere(partial)[0]
        raise FlightError(
            f"{where}: line {r + 2}: sensor {system.sensors[k].name!r} has some outputs but not all"
        )
    episode = table[:, col["episode"]] if "episode" in col else None
    try:
        return make_flight(
            system, table[:, col["t"]], pick(system.state), pick(system.controls), np.nan_to_num(z),
            valid, episode, source=os.fspath(path),
        )  # fmt: skip
    except FlightError as exc:
        raise FlightError(f"{where}: {exc}") from None


def load_log(path: str | os.PathLike[str], system: System | None = None) -> Flight:
    """A flight from ``.npz`` (:func:`load_flight`) or ``.csv`` (:func:`load_csv`, which needs
    ``system``)."""
    if str(path).lower().endswith(".csv"):
        if system is None:
            raise FlightError(f"CSV log {os.fspath(path)!r}: a system description is needed (--system)")
        return load_csv(path, system)
    return load_flight(path)
