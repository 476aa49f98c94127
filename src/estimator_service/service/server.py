"""The estimator as a zenoh network service (``python -m estimator_service`` / ``gpbf serve``).

Key expressions (``docs/protocol.md``): inputs ``gpbf/<blimp>/control`` and
``gpbf/<blimp>/camera/<k>``; output ``gpbf/<blimp>/belief``; errors ``gpbf/<blimp>/error``;
queryables ``gpbf/<blimp>/step``, ``gpbf/<blimp>/reset``, ``gpbf/<blimp>/status``; a
liveliness token ``gpbf/@service/<id>``. One session per blimp id, created on first contact
(default filter and model) or by a reset that names them.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import signal
import sys
import threading
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from estimator_service.factory import load_models, make_filter
from estimator_service.service.protocol import PROTOCOL_VERSION, encode
from estimator_service.service.session import Session, SessionSettings
from estimator_service.service.workers import WorkerPool

__all__ = ["EstimatorService", "ServiceConfig", "main", "zenoh_config"]

BLIMP_ID = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")
MAX_SESSIONS = 4096
LIVELINESS_PREFIX = "gpbf/@service"


@dataclass(frozen=True)
class ServiceConfig:
    """Service settings; ``filter``/``model`` are the defaults for new sessions."""

    model_dir: Path
    filter: str = "ekf"
    model: str = "gp"
    listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    connect: tuple[str, ...] = ()
    zenoh_config_file: Path | None = None
    n_particles: int = 2000
    workers: int = 2
    session: SessionSettings = field(default_factory=SessionSettings)
    service_id: str = field(default_factory=lambda: uuid.uuid4().hex[:12])


def zenoh_config(listen=("tcp/127.0.0.1:7447",), connect=(), file: Path | None = None) -> zenoh.Config:
    """Peer mode on loopback with multicast scouting off, unless a JSON5 file says otherwise."""
    if file is not None:
        return zenoh.Config.from_file(str(file))
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return cfg


def _model_version(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.glob("*.npz")):
        h.update(p.name.encode())
        h.update(str(p.stat().st_size).encode())
        h.update(str(p.stat().st_mtime_ns).encode())
    return h.hexdigest()[:16]


class EstimatorService:
    """Holds the zenoh session, the models, the estimator sessions and the declarations."""

    def __init__(self, config: ServiceConfig) -> None:
        self.config = config
        self._models: dict[str, Any] = {}
        self._filters: dict[tuple[str, str], Any] = {}
        self._sessions: dict[str, Session] = {}
        self._lock = threading.RLock()  # a new session builds its filter under the lock
        self._version = _model_version(config.model_dir)
        self._pool = WorkerPool(config.workers)
        self._build_filter(config.filter, config.model)  # fail fast on missing model files
        self.zenoh = zenoh.open(zenoh_config(config.listen, config.connect, config.zenoh_config_file))
        self._pubs: dict[str, Any] = {}
        self._decls = [
            self.zenoh.declare_subscriber("gpbf/*/control", self._on_sample),
            self.zenoh.declare_subscriber("gpbf/*/camera/*", self._on_sample),
            *(
                self.zenoh.declare_queryable(f"gpbf/*/{q}", self._on_query)
                for q in ("step", "reset", "status")
            ),
        ]
        self._token = self.zenoh.liveliness().declare_token(f"{LIVELINESS_PREFIX}/{config.service_id}")

    # -- models and filters, shared by sessions ------------------------------------------------------
    def _build_filter(self, filter_name: str, model: str):
        key = (filter_name, model)
        with self._lock:
            if key not in self._filters:
                if model not in self._models:
                    self._models[model] = load_models(self.config.model_dir, model)
                opts = {"n_particles": self.config.n_particles} if filter_name == "pf" else {}
                self._filters[key] = make_filter(filter_name, *self._models[model], **opts)
            return self._filters[key]

    def _publish(self, blimp: str, kind: str, payload: bytes) -> None:
        key = f"gpbf/{blimp}/{kind}"
        pub = self._pubs.get(key)
        if pub is None:
            pub = self._pubs.setdefault(key, self.zenoh.declare_publisher(key))
        pub.put(payload)

    def session(self, blimp: str) -> Session | None:
        with self._lock:
            s = self._sessions.get(blimp)
            if s is None and len(self._sessions) < MAX_SESSIONS:
                s = Session(
                    blimp,
                    self.config.filter,
                    self.config.model,
                    self.config.session,
                    self._build_filter,
                    lambda kind, p, b=blimp: self._publish(b, kind, p),
                    self._version,
                    pool=self._pool,
                )
                self._sessions[blimp] = s
            return s

    # -- zenoh callbacks: route and enqueue, nothing else --------------------------------------------
    def _route(self, key: str) -> tuple[str | None, str, Any]:
        parts = key.split("/")
        blimp = parts[1] if len(parts) >= 3 else ""
        kind = parts[2] if len(parts) >= 3 else ""
        extra = None
        if kind == "camera":
            extra = int(parts[3]) if len(parts) == 4 and parts[3].isdigit() else -1
        return (blimp if BLIMP_ID.match(blimp) else None), kind, extra

    def _on_sample(self, sample: zenoh.Sample) -> None:
        blimp, kind, extra = self._route(str(sample.key_expr))
        session = self.session(blimp) if blimp else None
        if session is None:
            return
        session.submit(kind, sample.payload.to_bytes(), None, extra)  # size is checked on decode

    def _on_query(self, query: zenoh.Query) -> None:
        blimp, kind, _ = self._route(str(query.key_expr))
        session = self.session(blimp) if blimp else None
        if session is None:
            query.reply_err(encode({"v": PROTOCOL_VERSION, "error": "invalid blimp id or too many sessions"}))
            return
        payload = query.payload.to_bytes() if query.payload is not None else b""
        session.submit(kind, payload, query)

    def close(self) -> None:
        """Stop taking input, let the workers finish what is queued, leave zenoh."""
        self._token.undeclare()
        for d in self._decls:
            d.undeclare()
        self._pool.stop()
        self.zenoh.close()


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="gpbf serve", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--models", type=Path, required=True, help="model folder written by 'gpbf train'")
    p.add_argument(
        "--filter",
        choices=("ekf", "ukf", "pf"),
        default="ekf",
        help="default filter of new sessions",
    )
    p.add_argument(
        "--model",
        choices=("param", "gp", "egp", "hetgp", "sparse"),
        default="gp",
        help="default model kind of new sessions",
    )
    p.add_argument(
        "--listen",
        action="append",
        default=None,
        help="zenoh endpoint to listen on (default tcp/127.0.0.1:7447; repeatable)",
    )
    p.add_argument("--connect", action="append", default=[], help="zenoh endpoint to connect to (repeatable)")
    p.add_argument(
        "--zenoh-config",
        type=Path,
        default=None,
        help="JSON5 zenoh config (client/router mode, other endpoints); overrides --listen/--connect",
    )
    p.add_argument("--particles", type=int, default=2000, help="particles of PF sessions")
    p.add_argument("--workers", type=int, default=2, help="worker threads shared by all sessions")
    p.add_argument("--blas-threads", type=int, default=0, help="BLAS threads (0: library default)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.blas_threads > 0:  # per-step linear algebra is small; threads only contend with zenoh's
        from threadpoolctl import threadpool_limits

        threadpool_limits(args.blas_threads)
    cfg = ServiceConfig(
        args.models,
        args.filter,
        args.model,
        tuple(args.listen or ("tcp/127.0.0.1:7447",)),
        tuple(args.connect),
        args.zenoh_config,
        args.particles,
        args.workers,
    )
    try:
        service = EstimatorService(cfg)
    except (OSError, ValueError, zenoh.ZError) as exc:
        print(f"gpbf serve: error: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print(
        f"gpbf serve: ready, service {cfg.service_id}, listening on {', '.join(cfg.listen)}",
        flush=True,
    )
    while not stop.wait(0.5):
        pass
    service.close()
    print("gpbf serve: stopped", flush=True)
    return 0
