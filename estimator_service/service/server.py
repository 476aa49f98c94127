"""The estimator as a zenoh network service (``python -m estimator_service`` / ``gpbf serve``).

Key expressions (``docs/protocol.md``): inputs ``gpbf/<blimp>/control`` and
``gpbf/<blimp>/camera/<k>``; output ``gpbf/<blimp>/belief``; errors ``gpbf/<blimp>/error``;
queryables ``gpbf/<blimp>/step``, ``gpbf/<blimp>/reset``, ``gpbf/<blimp>/status``; a
liveliness token ``gpbf/@service/<id>``. One session per blimp id, created by a ``reset``.

A fleet: several services on one zenoh network each see the others' liveliness tokens and
serve only the blimps they own (rendezvous hashing over the live services,
:func:`~estimator_service.service.keys.owner`); the others ignore that blimp's input.
When a service dies its blimps move to the survivors, which have no session for them: the
client re-creates each from its last belief (``EstimatorClient(failover=True)``).
"""

from __future__ import annotations

import os
import sys
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zenoh

from estimator_service.cli_args import Parser, add_filter_options, checked_int, model_kind
from estimator_service.factory import adaptation_defaults, load_models, make_filter, warm_up
from estimator_service.filters.particle import UPDATE_RULES
from estimator_service.service import keys
from estimator_service.service.batching import step_together
from estimator_service.service.config import (
    DEFAULT_ENDPOINT,
    SERVICE_LEASE_MS,
    describe,
    lease_in_effect_s,
    serve_until_stopped,
    zenoh_config,
    zenoh_message,
)
from estimator_service.service.inbox import ByteMeter
from estimator_service.service.limits import (
    CatchUpBudget,
    Limits,
    add_limit_options,
    fence_and_tick,
    limits_from,
)
from estimator_service.service.membership import Membership
from estimator_service.service.protocol import MAX_PAYLOAD, MSGPACK, NO_SESSION, PROTOCOL_VERSION, encode
from estimator_service.service.session import Session, SessionSettings
from estimator_service.service.workers import WorkerPool
from estimator_service.store import model_version, read_system
from estimator_service.system import System

if TYPE_CHECKING:
    from estimator_service.filters import EKF, PF, UKF
    from estimator_service.models.base import ObservationModel, PredictionModel

__all__ = ["EstimatorService", "ServiceConfig", "main", "service_filter", "zenoh_config"]


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
    adapt_rate: float | None = None  # None: the model folder's choice (factory.adaptation_defaults)
    workers: int = 2
    limits: Limits = field(default_factory=Limits)
    service_id: str = field(default_factory=lambda: uuid.uuid4().hex[:12])
    pf_update: str | None = None  # the PF's update_rule; None: the model kind's (factory.PF_UPDATE_RULES)

    def __post_init__(self) -> None:
        if self.pf_update not in (None, *UPDATE_RULES):
            raise ValueError(f"pf_update must be one of {UPDATE_RULES} or None, got {self.pf_update!r}")


def service_filter(
    config: ServiceConfig, system: System, filter_name: str, model: str,
    models: tuple[PredictionModel, ObservationModel],
) -> EKF | UKF | PF:  # fmt: skip
    """The filter the service runs for ``filter_name`` on ``model``'s fitted ``models``: the
    particle count and update rule from ``config``; for a Gaussian filter the model folder's adaptation
    defaults, with the configured rate (0 included: off) in place of the folder's."""
    opts: dict[str, object] = {"n_particles": config.n_particles}
    if config.pf_update is not None:
        opts["update_rule"] = config.pf_update
    if filter_name != "pf":
        opts = adaptation_defaults(config.model_dir, model)
        if config.adapt_rate is not None:
            opts["adapt_rate"] = config.adapt_rate
    return make_filter(filter_name, *models, system=system, model_kind=model, **opts)


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
        lim = config.limits
        budget = CatchUpBudget(  # a tenant share of 0: none
            lim.catch_up_share, lim.tenant_catch_up_share, lim.catch_up_burst_s, max_tenants=lim.max_sessions
        )
        queued = ByteMeter(config.limits.total_queue_bytes)
        self._settings = SessionSettings(self.system, config.limits, budget, queued)
        self.oversized = 0  # inputs refused in the zenoh callback, before any queue
        self._pool = WorkerPool(config.workers, step_together)
        self._build_filter(config.filter, config.model)  # fail fast on missing model files
        cfg_file = config.zenoh_config_file
        self.zenoh_cfg = zenoh_config(config.listen, config.connect, cfg_file, lease_ms=SERVICE_LEASE_MS)
        self.fence_s, self._watch_tick = fence_and_tick(
            config.limits.fence_after_s, lease_in_effect_s(self.zenoh_cfg)
        )
        self.zenoh = zenoh.open(self.zenoh_cfg)
        self._pubs: dict[str, Any] = {}
        self._stop = threading.Event()
        self._live = frozenset({config.service_id})  # the fleet as this service sees it (swapped whole)
        self._members = Membership(self.zenoh, config.service_id, self._lock, self._fleet_changed)
        self.fenced = 0  # sessions forgotten on waking from a freeze
        self.evicted = 0  # idle sessions closed at the cap or a tenant's quota for a new blimp
        self._tick = time.monotonic()  # the freeze watchdog's last tick
        # every field a callback reads exists before the first callback can run
        self._decls = [
            *(self.zenoh.declare_subscriber(keys.wildcard(k), self._on_sample) for k in keys.INPUTS),
            *(self.zenoh.declare_queryable(keys.wildcard(q), self._on_query) for q in keys.QUERIES),
            self.zenoh.declare_queryable(keys.sessions_key(config.service_id), self._on_list),
            self.zenoh.declare_queryable(keys.hello_key(config.service_id), self._on_hello),
        ]
        self._janitor = threading.Thread(target=self._expire_loop, name="estimator-janitor", daemon=True)
        self._janitor.start()
        self._watchdog = threading.Thread(target=self._watch, name="estimator-watchdog", daemon=True)
        self._watchdog.start()
        self._fleet = self.zenoh.liveliness().declare_subscriber(
            keys.liveliness_key("*"), self._members.on_token, history=True
        )
        self._token = self.zenoh.liveliness().declare_token(keys.liveliness_key(config.service_id))

    # -- models and filters, shared by sessions ------------------------------------------------------
    def _build_filter(self, filter_name: str, model: str):
        key = (filter_name, model)
        with self._lock:
            if key not in self._filters:
                if model not in self._models:
                    self._models[model] = load_models(self.config.model_dir, model)
                filt = service_filter(self.config, self.system, filter_name, model, self._models[model])
                warm_up(filt, self.system)  # caches now, not in a blimp's first step
                self._filters[key] = filt
            return self._filters[key]

    def _publish(self, blimp: str, kind: str, payload: bytes) -> None:
        key = keys.blimp_key(blimp, kind)
        pub = self._pubs.get(key)
        if pub is None:
            pub = self._pubs.setdefault(key, self.zenoh.declare_publisher(key, encoding=MSGPACK))
        pub.put(payload, encoding=MSGPACK)

    def session(self, blimp: str, create: bool = True) -> Session | str:
        """The blimp's session (created when ``create``), or why there is none."""
        with self._lock:
            s = self._sessions.get(blimp)
            if s is None and not create:
                why = "new blimp, service restarted, blimp moved or expired"
                return f"{NO_SESSION} {blimp!r}: send a reset ({why})"
            if s is None:
                full = self._make_room(blimp)
                if full is not None:
                    return full
                s = Session(
                    blimp,
                    self.config.filter,
                    self.config.model,
                    self._settings,
                    self._build_filter,
                    lambda kind, p, b=blimp: self._publish(b, kind, p),
                    self._version,
                    self.config.service_id,
                    pool=self._pool,
                )
                self._sessions[blimp] = s
            return s

    # -- the fleet ------------------------------------------------------------------------------------
    def _fleet_changed(self, live: frozenset[str]) -> None:
        """A verified service joined or one left (:class:`Membership`, under the lock): update
        the view and give up the blimps now owned elsewhere."""
        with self._lock:
            self._live = live
            moved = [b for b in self._sessions if not self._owns(b)]
            for b in moved:
                self._sessions.pop(b).stop()

    def _on_hello(self, query: zenoh.Query) -> None:
        query.reply(keys.hello_key(self.config.service_id), self._members.hello(), encoding=MSGPACK)

    def _owns(self, blimp: str) -> bool:
        return keys.owner(blimp, self._live) == self.config.service_id

    def fleet(self) -> list[str]:
        with self._lock:
            return sorted(self._live)

    # -- session lifecycle ---------------------------------------------------------------------------
    def _expire(self, now: float) -> int:
        """Close sessions idle for longer than the limit; returns how many."""
        ttl = self.config.limits.session_ttl_s
        if ttl <= 0:
            return 0
        with self._lock:
            old = [b for b, s in self._sessions.items() if s.idle_s(now) > ttl]
            for b in old:
                self._sessions.pop(b).stop()
        return len(old)

    def _make_room(self, blimp: str) -> str | None:
        """Room for a new blimp's session (under the lock), or why there is none: at its
        tenant's quota or at the session cap, the tenant's own least recently used session
        idle for ``evict_idle_s`` is closed first; at the cap, then the one idle the longest
        (a table filled by resets never followed by input frees up within that time)."""
        lim, tenant = self.config.limits, keys.tenant(blimp)
        wait = f"none idle for {lim.evict_idle_s:g} s (--evict-idle): close sessions ('close') or wait"
        at_quota = lim.session_quota and self._tenant_count(tenant) >= lim.session_quota
        if at_quota and self._expire(time.monotonic()):  # timed-out sessions go first
            at_quota = self._tenant_count(tenant) >= lim.session_quota
        if at_quota and not self._evict_idlest(tenant):
            quota = f"quota of {lim.session_quota} sessions (--session-quota)"
            return f"tenant {tenant!r} holds its {quota} and {wait}"
        if len(self._sessions) >= lim.max_sessions:
            self._expire(time.monotonic())
        if len(self._sessions) >= lim.max_sessions and not (
            self._evict_idlest(tenant) or self._evict_idlest(None)
        ):
            return f"session cap of {lim.max_sessions} reached and {wait}"
        return None

    def _tenant_count(self, tenant: str) -> int:
        return sum(1 for b in self._sessions if keys.tenant(b) == tenant)

    def _evict_idlest(self, tenant: str | None) -> bool:
        """Close the session idle the longest (of ``tenant``; of any with None) if it has been
        idle for ``evict_idle_s`` (under the lock); whether one was closed."""
        now = time.monotonic()
        idle = {
            b: s.idle_s(now) for b, s in self._sessions.items() if tenant is None or keys.tenant(b) == tenant
        }
        blimp = max(idle, key=idle.__getitem__, default=None)
        if blimp is None or idle[blimp] < self.config.limits.evict_idle_s:
            return False
        self._sessions.pop(blimp).stop()
        self.evicted += 1
        return True

    def _expire_loop(self) -> None:
        ttl = self.config.limits.session_ttl_s
        while not self._stop.wait(min(5.0, ttl / 4) if ttl > 0 else 5.0):
            self._expire(time.monotonic())

    def _watch(self) -> None:
        """Tick every :data:`~estimator_service.service.limits.WATCH_TICK_S` (shorter with a
        short fence); a late tick means the process was frozen."""
        while not self._stop.wait(self._watch_tick):
            self._fence_if_frozen(tick=True)

    def _fence_if_frozen(self, tick: bool = False) -> None:
        """Forget every session when this process's clock jumped by more than
        :attr:`fence_s` since the watchdog's last tick (it was frozen: its blimps may have
        moved). Lock-free unless frozen: the zenoh callbacks call it for every input."""
        now = time.monotonic()
        if now - self._tick <= self.fence_s:
            if tick:
                self._tick = now
            return
        with self._lock:
            if now - self._tick <= self.fence_s:  # another thread fenced first
                return
            self._tick = now
            stale = list(self._sessions.values())
            self._sessions.clear()
            self.fenced += len(stale)
        for s in stale:
            s.stop()

    def _close_session(self, blimp: str) -> bytes | None:
        """Close a session; its final reply, or None when another close or the expiry
        removed it first."""
        with self._lock:
            s = self._sessions.pop(blimp, None)
        if s is None:
            return None
        s.stop()
        return encode({"v": PROTOCOL_VERSION, "blimp": blimp, "closed": True, "steps": s.steps})

    def _on_list(self, query: zenoh.Query) -> None:
        now = time.monotonic()
        with self._lock:
            rows = [
                {"blimp": b, "filter": s.filter_name, "model": s.model_name, "steps": s.steps, "t": s.t,
                 "idle_s": round(s.idle_s(now), 3), "queue_bytes": s.queue_bytes}
                for b, s in self._sessions.items()
            ]  # fmt: skip
        body = {
            "v": PROTOCOL_VERSION, "service": self.config.service_id, "count": len(rows),
            "max_sessions": self.config.limits.max_sessions, "oversized": self.oversized, "sessions": rows,
            "fleet": self.fleet(), "unverified_tokens": self._members.refused, "fenced": self.fenced,
            "fence_s": self.fence_s,
            "evicted": self.evicted, "session_quota": self.config.limits.session_quota,
            "pending_tokens": self._members.pending,
        }  # fmt: skip
        # its own key, not the query's wildcard: replies of several services are not merged
        query.reply(keys.sessions_key(self.config.service_id), encode(body), encoding=MSGPACK)

    # -- zenoh callbacks: route and enqueue, nothing else --------------------------------------------
    def _refuse(self, blimp: str | None, kind: str, text: str, query: zenoh.Query | None = None) -> None:
        msg = encode({"v": PROTOCOL_VERSION, "blimp": blimp, "input": kind, "error": text})
        if query is not None:
            query.reply_err(msg, encoding=MSGPACK)
        elif blimp:
            self._publish(blimp, "error", msg)

    def _count_oversized(self) -> None:
        with self._lock:  # zenoh calls back from several threads
            self.oversized += 1

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self._fence_if_frozen()  # before a session input queued during a freeze meets stale state
        blimp, kind, extra = keys.parse_key(str(sample.key_expr))
        if blimp is None or not self._owns(blimp):
            return
        if len(sample.payload) > MAX_PAYLOAD:  # before anything is queued or created
            self._count_oversized()
            self._refuse(
                blimp, kind, f"payload of {len(sample.payload)} bytes exceeds the {MAX_PAYLOAD}-byte cap"
            )
            return
        session = self.session(blimp, create=False)
        if isinstance(session, str):
            self._refuse(blimp, kind, session)
            return
        session.submit(kind, sample.payload.to_bytes(), None, extra)

    def _on_query(self, query: zenoh.Query) -> None:
        self._fence_if_frozen()
        blimp, kind, _ = keys.parse_key(str(query.key_expr))
        if blimp is None:
            self._refuse(None, kind, keys.BLIMP_ID_RULE, query)
            return
        if not self._owns(blimp):  # another service of the fleet answers
            query.drop()
            return
        size = len(query.payload) if query.payload is not None else 0
        if size > MAX_PAYLOAD:
            self._count_oversized()
            self._refuse(blimp, kind, f"payload of {size} bytes exceeds the {MAX_PAYLOAD}-byte cap", query)
            return
        session = self.session(blimp, create=kind == "reset")
        if isinstance(session, str):
            self._refuse(blimp, kind, session, query)
        elif kind == "close":
            closed = self._close_session(blimp)
            if closed is None:  # closed, expired or moved since it was looked up
                self._refuse(blimp, kind, f"{NO_SESSION} {blimp!r}: already closed", query)
            else:
                query.reply(query.key_expr, closed, encoding=MSGPACK)
        else:
            session.submit(kind, query.payload.to_bytes() if query.payload is not None else b"", query)

    def close(self) -> None:
        """Stop taking input, let the workers finish what is queued, leave zenoh."""
        self._stop.set()
        self._fleet.undeclare()
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
        help="JSON5 zenoh config (client mode, authentication, ...) merged onto these options: what it "
        "sets wins; --listen and --connect apply where it sets none (docs/protocol.md)",
    )  # fmt: skip
    p.add_argument(
        "--workers", type=checked_int(1, 64), default=2, help="worker threads shared by all sessions"
    )
    add_limit_options(p)
    p.add_argument(
        "--blas-threads", type=checked_int(0, 256), default=0,
        help="BLAS threads (0: the cores over the workers, at least 1)",
    )  # fmt: skip
    return p


def blas_threads_for(requested: int, workers: int, cores: int | None = None) -> int:
    """BLAS threads per process: ``requested``, or (0) the cores shared out over the workers.

    Each worker runs its own filter steps; with the library default (one BLAS thread per
    core) in every worker, OpenBLAS's threads spin against each other: exact GP-EKF on 2
    cores, 2 workers, 25 blimps at 4 Hz: p99 3.2-6.4 s with 2 BLAS threads, 108 ms with 1.
    """
    if requested > 0:
        return requested
    return max(1, (cores or os.cpu_count() or 1) // workers)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from threadpoolctl import threadpool_limits

    threadpool_limits(blas_threads_for(args.blas_threads, args.workers))
    try:
        cfg = ServiceConfig(
            args.models,
            args.filter,
            model_kind(args),
            tuple(args.listen or (DEFAULT_ENDPOINT,)),
            tuple(args.connect),
            args.zenoh_config,
            args.particles,
            args.adapt,
            args.workers,
            limits_from(args),
            pf_update=args.pf_update,
        )
        service = EstimatorService(cfg)
    except (OSError, ValueError, zenoh.ZError) as exc:
        print(f"gpbf serve: error: {zenoh_message(exc)}", file=sys.stderr)
        return 2
    return serve_until_stopped(
        "gpbf serve", f"service {cfg.service_id}, {describe(service.zenoh_cfg)}", service.close
    )
