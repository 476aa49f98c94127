"""The zenoh configuration the service and its clients start from."""

from __future__ import annotations

import json
import re
import signal
import threading
from collections.abc import Callable
from pathlib import Path

import zenoh

__all__ = [
    "DEFAULT_ENDPOINT",
    "SERVICE_LEASE_MS",
    "describe",
    "lease_in_effect_s",
    "serve_until_stopped",
    "zenoh_config",
    "zenoh_message",
]

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
#: the link lease a service announces (zenoh's default is 10 s): a service that stops answering
#: zenoh's keep-alives (four per lease, sent by zenoh's own threads) is dropped by the others,
#: and its blimps move to the survivors, after this long
SERVICE_LEASE_MS = 2000
_LEASE_KEY = "transport/link/tx/lease"


_RUST_PLACE = re.compile(r"\s+at /\S+\.rs:\d+\.?")  # " at /root/.cargo/.../endpoint.rs:615."
_WRAPPED = re.compile(  # Json5Err(Message { msg: "...", location: Some(Location { line: 1, column: 10 }) })
    r'(?:\w+Err\()?Message \{ msg: "(?P<msg>.*?)", location: '
    r"(?:Some\(Location \{ line: (?P<line>\d+), column: (?P<col>\d+) \}\)|None) \}\)?"
)


def _plain(m: re.Match) -> str:
    where = f" (line {m['line']}, column {m['col']})" if m["line"] else ""
    return m["msg"].rstrip(".:") + where


_PARSER_REPORT = re.compile(r"-->\s*(?P<line>\d+):(?P<col>\d+).*?\n\s*=\s*(?P<msg>[^\n]+)", re.S)


def zenoh_message(exc: BaseException) -> str:
    """A zenoh error as a user reads it, on one line: without Rust source paths and internal
    structures; a JSON5 parser's drawing of the place (``--> 3:7``, the line, a caret) as
    ``message (line 3, column 7)``."""
    text = _WRAPPED.sub(_plain, _RUST_PLACE.sub("", str(exc))).strip()
    text = _PARSER_REPORT.sub(lambda m: f"{m['msg'].strip()} (line {m['line']}, column {m['col']})", text)
    return " ".join(text.split())


def lease_in_effect_s(cfg: zenoh.Config) -> float:
    """The link lease ``cfg`` announces, in seconds (the others drop a peer silent this long)."""
    return float(json.loads(cfg.get_json(_LEASE_KEY))) / 1000.0


def zenoh_config(
    listen=(DEFAULT_ENDPOINT,), connect=(), file: Path | None = None, lease_ms: int | None = None
) -> zenoh.Config:
    """:func:`_config`, announcing a link lease of ``lease_ms`` unless the file sets another
    than zenoh's default (10 s); a bad endpoint or configuration file is a ValueError naming
    it."""
    try:
        cfg = _config(listen, connect, file)
        if lease_ms is not None and cfg.get_json(_LEASE_KEY) == zenoh.Config().get_json(_LEASE_KEY):
            cfg.insert_json5(_LEASE_KEY, str(int(lease_ms)))
        return cfg
    except zenoh.ZError as exc:
        said = zenoh_message(exc)
        if file is None:  # the place is in the JSON built from the options, not the user's
            said = re.sub(r" \(line \d+, column \d+\)$", "", said)
        raise ValueError(f"{_culprit(listen, connect, file)}: {said}") from None


def _culprit(listen, connect, file: Path | None) -> str:
    """The option a refused configuration came from: the file, or the first endpoint that
    zenoh refuses alone (``--listen X`` or ``--connect X``)."""
    if file is not None:
        return f"--zenoh-config {file}"
    for option, endpoints in (("--listen", listen), ("--connect", connect)):
        for e in endpoints:
            try:
                _config([e] if option == "--listen" else [], [e] if option == "--connect" else [], None)
            except zenoh.ZError:
                return f"{option} {e}"
    return f"endpoints {[*listen, *connect]}"


def _config(listen, connect, file: Path | None) -> zenoh.Config:
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


def serve_until_stopped(prog: str, ready: str, close: Callable[[], None]) -> int:
    """Print ``prog: ready, <ready>``, wait for SIGINT or SIGTERM, ``close()``, print that it
    stopped; the exit code 0 (the process plumbing of ``gpbf serve`` and ``gpbf router``)."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print(f"{prog}: ready, {ready}", flush=True)
    while not stop.wait(0.5):
        pass
    close()
    print(f"{prog}: stopped", flush=True)
    return 0
