"""The estimator as a zenoh network service (``python -m estimator_service`` / ``gpbf serve``).

Key expressions (``docs/protocol.md``): inputs ``gpbf/<blimp>/control`` and
``gpbf/<blimp>/camera/<k>``; output ``gpbf/<blimp>/belief``; errors ``gpbf/<blimp>/error``;
queryables ``gpbf/<blimp>/step``, ``gpbf/<blimp>/reset``, ``gpbf/<blimp>/status``; a
liveliness token ``gpbf/@service/<id>``. One session per blimp id, created on first contact
(default filter and model) or by a reset that names them.
"""

from __future__ import annotations

import signal
import sys
import threading
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from estimator_service.cli_args import Parser, add_filter_options, checked_int
from estimator_service.factory import load_models, make_filter
from estimator_service.service import keys
from estimator_service.service.config import DEFAULT_ENDPOINT, zenoh_config
from estimator_service.service.protocol import PROTOCOL_VERSION, encode
from estimator_service.service.session import Session, SessionSettings, step_together
from estimator_service.service.workers import WorkerPool
from estimator_service.store import model_version, read_system

__all__ = ["EstimatorService", "ServiceConfig", "main", "zenoh_config"]

MAX_SESSIONS = 4096


@dataclass(frozen=True)
class ServiceConfig:
    """Service settings; ``filter``/``model`` are the defaults for new sessions."""

    model_dir: Path
    filter: str = "ekf"
    model: str = "gp"
    listen: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    connect: tuple[str, ...] = ()
    zenoh_config_file: Path | None = None
    n_particles: int = 2000
    workers: int = 2
    service_id: str = field(default_factory=lambda: uuid.uuid4().hex[:12])


class EstimatorService:
    """Holds the zenoh session, the models, the estimator sessions and the declarations."""

    def __init__(self, config: ServiceConfig) -> None:
        self.config = config
        self._models: dict[str, Any] = {}
        self._filters: dict[tuple[str, str], Any] = {}
        self._sessions: dict[str, Session] = {}
        self._lock = threading.RLock()  # a new session builds its filter under the lock
        self._version = model_version(config.model_dir)  # refuses an incomplete or mixed folder
        self.system = read_system(config.model_dir)
        self._settings = SessionSettings(self.system)
        self._pool = WorkerPool(config.workers, step_together)
        self._build_filter(config.filter, config.model)  # fail fast on missing model files
        self.zenoh = zenoh.open(zenoh_config(config.listen, config.connect, config.zenoh_config_file))
        self._pubs: dict[str, Any] = {}
        self._decls = [
            *(self.zenoh.declare_subscriber(keys.wildcard(k), self._on_sample) for k in keys.INPUTS),
            *(self.zenoh.declare_queryable(keys.wildcard(q), self._on_query) for q in keys.QUERIES),
        ]
        self._token = self.zenoh.liveliness().declare_token(keys.liveliness_key(config.service_id))

    # -- models and filters, shared by sessions ------------------------------------------------------
    def _build_filter(self, filter_name: str, model: str):
        key = (filter_name, model)
        with self._lock:
            if key not in self._filters:
                if model not in self._models:
                    self._models[model] = load_models(self.config.model_dir, model)
                opts = {"n_particles": self.config.n_particles} if filter_name == "pf" else {}
                self._filters[key] = make_filter(
                    filter_name, *self._models[model], system=self.system, **opts
                )
            return self._filters[key]

    def _publish(self, blimp: str, kind: str, payload: bytes) -> None:
        key = keys.blimp_key(blimp, kind)
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
                    self._settings,
                    self._build_filter,
                    lambda kind, p, b=blimp: self._publish(b, kind, p),
                    self._version,
                    pool=self._pool,
                )
                self._sessions[blimp] = s
            return s

    # -- zenoh callbacks: route and enqueue, nothing else --------------------------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        blimp, kind, extra = keys.parse_key(str(sample.key_expr))
        session = self.session(blimp) if blimp else None
        if session is None:
            return
        session.submit(kind, sample.payload.to_bytes(), None, extra)  # size is checked on decode

    def _on_query(self, query: zenoh.Query) -> None:
        blimp, kind, _ = keys.parse_key(str(query.key_expr))
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


def build_parser() -> Parser:
    p = Parser(prog="gpbf serve", description=__doc__)
    add_filter_options(p, models_required=True)
    p.add_argument(
        "--listen", action="append", default=None,
        help=f"zenoh endpoint to listen on (repeatable; none given: {DEFAULT_ENDPOINT})",
    )  # fmt: skip
    p.add_argument("--connect", action="append", default=[], help="zenoh endpoint to connect to (repeatable)")
    p.add_argument(
        "--zenoh-config", type=Path, default=None,
        help="JSON5 zenoh config (client/router mode, other endpoints); overrides --listen/--connect",
    )  # fmt: skip
    p.add_argument(
        "--workers", type=checked_int(1, 64), default=2, help="worker threads shared by all sessions"
    )
    p.add_argument(
        "--blas-threads", type=checked_int(0, 256), default=0, help="BLAS threads (0: library default)"
    )
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
        tuple(args.listen or (DEFAULT_ENDPOINT,)),
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
