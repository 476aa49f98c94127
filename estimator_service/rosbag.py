"""ROS bags (rosbag1, rosbag2 with SQLite or MCAP storage) as event logs.

Read through the maintained ``rosbags`` package (``pip install 'gpbf[ros]'``). A JSON
*topic mapping* says which topic feeds which stream of the
:class:`~estimator_service.events.EventLog` and which message fields are its values::

    {
      "time": "header",
      "streams": {
        "state":   {"topic": "/mocap/rover", "fields": ["x", "y", "theta"]},
        "control": {"topic": "/cmd_vel", "fields": ["linear.x", "angular.z"]},
        "lm6":     {"topic": "/landmarks", "fields": ["range", "bearing"],
                    "where": {"id": 6}}
      }
    }

- ``time``: ``"header"`` (default) stamps an event with its message's ``header.stamp``
  where it has one, else with the time it was logged; ``"log"`` always with the latter.
- ``fields``: dotted paths into the message, in the order of the state components, the
  controls or the sensor's outputs; ``"yaw:<path>"`` takes the heading (rad) of the
  quaternion at ``<path>`` (e.g. ``"yaw:pose.pose.orientation"``).
- ``where`` (optional): field values a message must have to belong to the stream (one
  topic carrying the readings of several sensors).

Every stream name must be ``state``, ``control`` or a sensor of the description; a topic
or field that the bag lacks is an error naming it.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

from estimator_service.events import EventLog
from estimator_service.flight import FlightError
from estimator_service.system import System

__all__ = ["TopicMapping", "load_rosbag", "read_mapping"]

TopicMapping = dict[str, Any]
_TIME_RULES = ("header", "log")


def read_mapping(source: str | os.PathLike[str] | TopicMapping) -> TopicMapping:
    """A checked topic mapping from a dict or a JSON file."""
    where = "topic mapping"
    if not isinstance(source, dict):
        where = f"topic mapping {os.fspath(source)!r}"
        try:
            source = json.loads(Path(source).read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise FlightError(f"{where}: unreadable ({exc})") from None
    if not isinstance(source, dict) or not isinstance(source.get("streams"), dict):
        raise FlightError(f"{where}: must be an object with 'streams' {{name: {{topic, fields}}}}")
    if source.get("time", "header") not in _TIME_RULES:
        raise FlightError(f"{where}: 'time' must be one of {_TIME_RULES}, got {source.get('time')!r}")
    for name, spec in source["streams"].items():
        ok = isinstance(spec, dict) and isinstance(spec.get("topic"), str)
        ok = ok and isinstance(spec.get("fields"), list) and all(isinstance(f, str) for f in spec["fields"])
        if not ok or not isinstance(spec.get("where", {}), dict):
            raise FlightError(
                f"{where}: stream {name!r} must be {{'topic': str, 'fields': [str, ...], 'where': {{...}}}}"
            )
    return source


def load_rosbag(
    path: str | os.PathLike[str], system: System, mapping: str | os.PathLike[str] | TopicMapping
) -> EventLog:
    """The event log of the bag at ``path`` (a rosbag1 ``.bag`` file or a rosbag2 folder,
    SQLite or MCAP) under ``mapping`` (:func:`read_mapping`)."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise FlightError("reading ROS bags needs the 'ros' extra: pip install 'gpbf[ros]'") from None
    spec = read_mapping(mapping)
    where = f"ROS bag {os.fspath(path)!r}"
    streams: dict[str, tuple[list[float], list[list[float]]]] = {n: ([], []) for n in spec["streams"]}
    try:
        reader = AnyReader([Path(path)], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except Exception as exc:  # the library raises its own error types per format
        raise FlightError(f"{where}: unreadable ({exc})") from None
    try:
        by_topic = _connections(reader, spec, where)
        for conn, logged, raw in reader.messages(connections=[c for cs in by_topic.values() for c in cs]):
            msg = reader.deserialize(raw, conn.msgtype)
            for name, s in spec["streams"].items():
                if s["topic"] != conn.topic or not _matches(msg, s.get("where", {}), name, where):
                    continue
                t = _stamp(msg) if spec.get("time", "header") == "header" else None
                streams[name][0].append(logged * 1e-9 if t is None else t)
                streams[name][1].append([_field(msg, f, name, where) for f in s["fields"]])
    finally:
        reader.close()
    try:
        return EventLog.from_streams(system, streams)
    except FlightError as exc:
        raise FlightError(f"{where}: {exc}") from None


def _connections(reader, spec: TopicMapping, where: str) -> dict[str, list]:
    topics: dict[str, list] = {}
    for conn in reader.connections:
        topics.setdefault(conn.topic, []).append(conn)
    for name, s in spec["streams"].items():
        if s["topic"] not in topics:
            raise FlightError(
                f"{where}: stream {name!r}: no topic {s['topic']!r}; the bag has {sorted(topics)}"
            )
    return {s["topic"]: topics[s["topic"]] for s in spec["streams"].values()}


def _stamp(msg: Any) -> float | None:
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if stamp is None:
        return None
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def _get(msg: Any, path: str, name: str, where: str) -> Any:
    value = msg
    for part in path.split("."):
        if not hasattr(value, part):
            raise FlightError(f"{where}: stream {name!r}: message {type(msg).__name__} has no field {path!r}")
        value = getattr(value, part)
    return value


def _field(msg: Any, path: str, name: str, where: str) -> float:
    if path.startswith("yaw:"):
        q = _get(msg, path[4:], name, where)
        return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
    value = _get(msg, path, name, where)
    try:
        return float(value)
    except (TypeError, ValueError):
        raise FlightError(f"{where}: stream {name!r}: field {path!r} is not a number") from None


def _matches(msg: Any, conditions: dict[str, Any], name: str, where: str) -> bool:
    return all(_get(msg, path, name, where) == value for path, value in conditions.items())
