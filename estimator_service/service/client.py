"""The client side of the zenoh estimator service.

:class:`EstimatorClient` talks to one blimp's session: ``reset`` it, then either
``step`` in lock-step (a zenoh query per step: control + sensor frames in, belief out)
or stream (``stream=True``; ``publish_control`` / ``publish_camera``; beliefs arrive on a
subscriber and are read with ``next_belief``). :func:`spawn_service` starts the service
as another process on a local port (:func:`free_port`), as the demo, the tests and the
benchmarks do.
"""

from __future__ import annotations

import itertools
import logging
import os
import queue
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import zenoh

from estimator_service.service import keys
from estimator_service.service.config import zenoh_config
from estimator_service.service.protocol import (
    MSGPACK,
    NO_SESSION,
    PROTOCOL_VERSION,
    decode,
    decode_belief,
    encode,
)

__all__ = [
    "EstimatorClient",
    "NoReply",
    "ServiceError",
    "SessionLost",
    "free_port",
    "list_sessions",
    "open_session",
    "services",
    "spawn_service",
]


log = logging.getLogger("estimator_service.client")


ZENOH_TIMEOUT = "Timeout"  # the error reply zenoh itself gives a query no queryable answered in time


class ServiceError(RuntimeError):
    """The service answered with an error, or did not answer."""


class NoReply(ServiceError):
    """No service answered in time (none runs, or the owner of the blimp just died)."""


class SessionLost(ServiceError):
    """The service has no session for the blimp (it restarted, expired it, or the blimp moved
    to another service of the fleet)."""


def open_session(connect: Sequence[str] = ("tcp/127.0.0.1:7447",), config_file=None) -> zenoh.Session:
    """A zenoh peer that connects to the service's endpoint(s); no listening, no scouting."""
    return zenoh.open(zenoh_config(listen=(), connect=tuple(connect), file=config_file))


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now (for a service started next)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def spawn_service(
    models: str | os.PathLike[str], port: int, *options: str,
    command: Sequence[str] = (sys.executable, "-m", "estimator_service"), merge_stderr: bool = True,
    cwd: str | os.PathLike[str] | None = None,
) -> tuple[subprocess.Popen, str]:  # fmt: skip
    """Start ``gpbf serve --models MODELS OPTIONS --listen tcp/127.0.0.1:PORT`` as another
    process (``command`` replaces ``python -m estimator_service``, e.g. by an instrumented
    launcher); return it and its ready line once it has printed that line.

    ``merge_stderr`` sends the service's stderr to the same pipe as its stdout. Raises
    :class:`RuntimeError` with what the service printed when it exits instead.
    """
    proc = subprocess.Popen(
        [*command, "--models", os.fspath(models), *options, "--listen", f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT if merge_stderr else None, text=True, cwd=cwd,
    )  # fmt: skip
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if "ready" not in line:
        proc.kill()
        raise RuntimeError(f"estimator service did not start: {line}{proc.stdout.read()}")
    return proc, line.strip()


def list_sessions(session: zenoh.Session, timeout: float = 2.0) -> list[dict[str, Any]]:
    """Every live service's ``sessions`` reply (its sessions, cap and view of the fleet)."""
    replies = session.get(
        keys.sessions_key("*"), target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
        timeout=timeout,
    )  # fmt: skip
    return [decode(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]


def services(session: zenoh.Session, timeout: float = 2.0) -> list[str]:
    """Ids of the estimator services currently alive (liveliness tokens)."""
    replies = session.liveliness().get(keys.liveliness_key("*"), timeout=timeout)
    return sorted(str(r.ok.key_expr).rsplit("/", 1)[-1] for r in replies if r.ok is not None)


class EstimatorClient:
    """One blimp's view of the service."""

    def __init__(
        self, session: zenoh.Session, blimp: str, timeout: float = 10.0, *, stream: bool = False,
        failover: bool = False, attempt_timeout: float = 0.5, failover_s: float = 2.0,
        on_resync: Callable[[str, dict[str, Any]], None] | None = None,
    ) -> None:  # fmt: skip
        """``failover``: a query waits ``attempt_timeout`` for a reply and is sent again until
        ``failover_s`` has passed, so a fleet's surviving service takes over a dead owner's
        blimp. Whenever the service answers that it has no session, the client re-creates it
        from the last belief it received (a ``reset`` to that mean, covariance and time),
        counts it in ``resyncs`` and reports it through ``on_resync(blimp, last_belief)`` and
        a warning on the ``estimator_service.client`` logger. ``blimp``: ``[<tenant>.]<name>``
        (:data:`~estimator_service.service.keys.BLIMP_ID`); another id raises ValueError."""
        if not isinstance(blimp, str) or not keys.BLIMP_ID.fullmatch(blimp):
            raise ValueError(f"blimp={blimp!r}: {keys.BLIMP_ID_RULE}")
        self.session, self.blimp = session, blimp
        self.timeout = attempt_timeout if failover else timeout
        self.failover, self.failover_s, self.on_resync = failover, failover_s, on_resync
        self.resyncs = 0
        self._last: dict[str, Any] | None = None
        self._seq = 0
        self._beliefs: queue.Queue = queue.Queue()
        self._errors: queue.Queue = queue.Queue()
        # Streamed beliefs only when asked for: a lock-step client gets each belief as the
        # query's reply, and a subscription would queue a copy of every one, unread.
        self._sub = (
            session.declare_subscriber(
                keys.blimp_key(blimp, "belief"), lambda s: self._beliefs.put(s.payload.to_bytes())
            )
            if stream
            else None
        )
        self._err = session.declare_subscriber(
            keys.blimp_key(blimp, "error"), lambda s: self._errors.put(s.payload.to_bytes())
        )
        self._pubs: dict[str, Any] = {}
        self._queriers: dict[str, Any] = {}
        self._lock = threading.Lock()

    def _next_seq(self) -> int:
        with self._lock:
            self._seq += 1
            return self._seq

    def query(
        self, kind: str, message: dict[str, Any] | None = None, raw: bytes | None = None
    ) -> dict[str, Any]:
        """Send a query (``step``, ``reset``, ``status``) and decode its single reply."""
        payload = raw if raw is not None else (encode(message) if message is not None else None)
        querier = self._queriers.get(kind)
        if querier is None:  # declared once per key: a lock-step loop skips the per-query routing set-up
            querier = self._queriers[kind] = self.session.declare_querier(
                keys.blimp_key(self.blimp, kind), timeout=self.timeout, target=zenoh.QueryTarget.ALL
            )
        handler = querier.get(payload=payload, encoding=MSGPACK)
        try:  # the first reply is the answer: no wait for the query's final message
            r = handler.recv()
        except zenoh.ZError:  # closed without a reply
            raise NoReply(self._silent(kind)) from None
        if r.ok is None:
            raw_err = r.err.payload.to_bytes()
            try:
                text = decode(raw_err).get("error", "unknown error")
            except ValueError:
                text = raw_err.decode("utf-8", "replace")  # zenoh's own errors, e.g. Timeout
                if text == ZENOH_TIMEOUT:  # a hung service: as no reply (failover retries it)
                    raise NoReply(f"{self._silent(kind)} ({text})") from None
            error = SessionLost if str(text).startswith(NO_SESSION) else ServiceError
            raise error(f"{kind} for blimp {self.blimp!r}: {text}")
        body = r.ok.payload.to_bytes()
        if kind not in ("step", "reset"):
            return decode(body)
        self._last = decode_belief(body)
        return self._last

    def _silent(self, kind: str) -> str:
        return f"no reply to {kind} for blimp {self.blimp!r} within {self.timeout} s"

    def _with_failover(self, send: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        """``send()``, re-sent while no service answers (``failover``) and after re-creating a
        lost session from the last belief, until ``failover_s`` has passed."""
        deadline = time.monotonic() + (self.failover_s if self.failover else 0.0)
        for attempt in itertools.count():
            try:
                return send()
            except SessionLost:
                if self._last is None or (attempt >= 2 and time.monotonic() > deadline):
                    raise
                try:
                    self._resync()
                except NoReply:
                    if time.monotonic() > deadline:
                        raise
            except NoReply:
                if time.monotonic() > deadline:
                    raise
        raise AssertionError("unreachable")

    def _resync(self) -> None:
        last = self._last
        self.reset(last["mean"], cov=last["cov"], t=last["t"], filter=last["filter"], model=last["model"])
        self.resyncs += 1
        log.warning("blimp %r: session re-created from its last belief (t = %s)", self.blimp, last["t"])
        if self.on_resync is not None:
            self.on_resync(self.blimp, last)

    def reset(
        self,
        mean: np.ndarray,
        std: np.ndarray | None = None,
        cov: np.ndarray | None = None,
        *,
        t: float = 0.0,
        filter: str | None = None,
        model: str | None = None,
        seed: int = 0,
    ) -> dict[str, Any]:
        """(Re)start the blimp's session at ``N(mean, cov or diag(std^2))``, time ``t``."""
        msg: dict[str, Any] = {
            "v": PROTOCOL_VERSION,
            "seq": self._next_seq(),
            "t": float(t),
            "mean": [float(x) for x in mean],
            "seed": seed,
        }
        if cov is not None:
            msg["cov"] = [float(x) for x in np.ravel(cov)]
        else:
            msg["std"] = [float(x) for x in std]
        if filter:
            msg["filter"] = filter
        if model:
            msg["model"] = model
        return self.query("reset", msg)

    def step(self, u: np.ndarray, frames: list[list[Any]], t: float) -> dict[str, Any]:
        """Lock-step: predict with ``u`` to time ``t``, update with ``frames``; the new belief."""
        msg = {
            "v": PROTOCOL_VERSION,
            "seq": self._next_seq(),
            "t": float(t),
            "u": [float(x) for x in u],
            "frames": frames,
        }
        return self._with_failover(lambda: self.query("step", msg))

    def status(self) -> dict[str, Any]:
        return self.query("status")

    def close_session(self) -> dict[str, Any]:
        """End the blimp's session on the service (its state is gone)."""
        return self.query("close")

    def _put(self, key: str, payload: bytes) -> None:
        pub = self._pubs.get(key)
        if pub is None:
            pub = self._pubs[key] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK, encoding=MSGPACK
            )
        pub.put(payload, encoding=MSGPACK)

    def publish_control(self, u: np.ndarray, t: float) -> None:
        msg = {"v": PROTOCOL_VERSION, "seq": self._next_seq(), "t": float(t), "u": [float(x) for x in u]}
        self._put(keys.blimp_key(self.blimp, "control"), encode(msg))

    def publish_camera(self, camera: int, ellipse: Sequence[float] | None, t: float) -> None:
        msg = {
            "v": PROTOCOL_VERSION,
            "seq": self._next_seq(),
            "t": float(t),
            "ellipse": None if ellipse is None else [float(x) for x in ellipse],
        }
        self._put(keys.camera_key(self.blimp, camera), encode(msg))

    def publish_raw(self, kind: str, payload: bytes) -> None:
        """Send arbitrary bytes on an input key (for tests of the service's validation)."""
        self._put(keys.blimp_key(self.blimp, kind), payload)

    def next_belief(self, timeout: float | None = None) -> dict[str, Any]:
        """The next streamed belief (blocks up to ``timeout``)."""
        if self._sub is None:
            raise ServiceError("streamed beliefs need EstimatorClient(..., stream=True)")
        try:
            return decode_belief(self._beliefs.get(timeout=timeout or self.timeout))
        except queue.Empty:
            raise ServiceError(f"no belief for blimp {self.blimp!r} within the timeout") from None

    def errors(self, wait: float = 0.0) -> list[dict[str, Any]]:
        """Error messages received so far (after waiting ``wait`` seconds)."""
        if wait:
            time.sleep(wait)
        out = []
        while not self._errors.empty():
            out.append(decode(self._errors.get_nowait()))
        return out

    def close(self) -> None:
        for d in (self._sub, self._err, *self._pubs.values(), *self._queriers.values()):
            if d is not None:
                d.undeclare()
