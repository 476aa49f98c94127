"""The zenoh configuration the service and its clients start from."""

from __future__ import annotations

import json
from pathlib import Path

import zenoh

__all__ = ["DEFAULT_ENDPOINT", "zenoh_config"]

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


def zenoh_config(listen=(DEFAULT_ENDPOINT,), connect=(), file: Path | None = None) -> zenoh.Config:
    """Peer mode on loopback with multicast scouting off, unless a JSON5 file says otherwise."""
    if file is not None:
        return zenoh.Config.from_file(str(file))
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return cfg
