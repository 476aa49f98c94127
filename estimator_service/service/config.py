"""The zenoh configuration the service and its clients start from."""

from __future__ import annotations

import json
from pathlib import Path

import zenoh

__all__ = ["DEFAULT_ENDPOINT", "describe", "zenoh_config"]

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


def zenoh_config(listen=(DEFAULT_ENDPOINT,), connect=(), file: Path | None = None) -> zenoh.Config:
    """Peer mode on loopback with multicast scouting off.

    A JSON5 ``file`` is merged onto these safe defaults: what it sets wins, but a file that
    does not mention ``listen`` keeps the loopback endpoints (``listen``), one that does not
    mention ``connect`` takes ``connect``, and one that does not mention ``multicast`` keeps
    multicast scouting off (``{}`` changes nothing).
    """
    if file is not None:
        cfg = zenoh.Config.from_file(str(file))
        unset = zenoh.Config()  # what a file that does not set a key leaves
        if cfg.get_json("scouting/multicast/enabled") == unset.get_json("scouting/multicast/enabled"):
            cfg.insert_json5("scouting/multicast/enabled", "false")
        mode_set = cfg.get_json("mode") != unset.get_json("mode")
        if not mode_set and cfg.get_json("listen/endpoints") == unset.get_json("listen/endpoints"):
            cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
        if connect and cfg.get_json("connect/endpoints") == unset.get_json("connect/endpoints"):
            cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
        return cfg
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return cfg


def describe(cfg: zenoh.Config) -> str:
    """``mode peer, listening on [...], connecting to [...]``: what a configuration does."""
    mode = json.loads(cfg.get_json("mode") or "null") or "peer"

    def endpoints(key: str) -> list[str]:
        value = json.loads(cfg.get_json(key) or "null")
        if isinstance(value, dict):  # per-mode defaults
            value = value.get(mode, [])
        return list(value or [])

    return (
        f"mode {mode}, listening on {endpoints('listen/endpoints') or 'nothing'}, "
        f"connecting to {endpoints('connect/endpoints') or 'nothing'}"
    )
