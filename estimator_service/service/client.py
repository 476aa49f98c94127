"""The client side of the zenoh estimator service.

:class:`EstimatorClient` talks to one blimp's session: ``reset`` it, then either
``step`` in lock-step (a zenoh query per step: control + sensor frames in, belief out)
or stream (``stream=True``; ``publish_control`` / ``publish_camera``; beliefs arrive on a
subscriber and are read with ``next_belief``). :func:`spawn_service` starts the service
as another process on a local port (:func:`free_port`), as the demo, the tests and the
benchmarks do.
"""

from __future__ import annotations

import os
import queue
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import zenoh

from estimator_service.service import keys
from estimator_service.service.config import zenoh_config
from estimator_service.service.protocol import MSGPACK, PROTOCOL_VERSION, decode, decode_belief, encode

__all__ = [
    "EstimatorClient",
    "ServiceError",
    "free_port",
    "open_session",
    "services",
    "spawn_service",
]


class ServiceError(RuntimeError):
    """The service answered with an error, or did not answer."""


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
) -> tuple[subprocess.Popen, str]:  # fmt: skip
    """Start ``gpbf serve --models MODELS OPTIONS --listen tcp/127.0.0.1:PORT`` as another
    process (``command`` replaces ``python -m estimator_service``, e.g. by an instrumented
    launcher); return it and its ready line once it has printed that line.

    ``merge_stderr`` sends the service's stderr to the same pipe as its stdout. Raises
    :class:`RuntimeError` with what the service printed when it exits instead.
    """
    proc = subprocess.Popen(
        [*command, "--models", os.fspath(models), *options, "--listen", f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT if merge_stderr else None, text=True,
    )  # fmt: skip
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if "ready" not in line:
        proc.kill()
        raise RuntimeError(f"estimator service did not start: {line}{proc.stdout.read()}")
    return proc, line.strip()


def services(session: zenoh.Session, timeout: float = 2.0) -> list[str]:
    """Ids of the estimator services currently alive (liveliness tokens)."""
    replies = session.liveliness().get(keys.liveliness_key("*"), timeout=timeout)
    return sorted(str(r.ok.key_expr).rsplit("/", 1)[-1] for r in replies if r.ok is not None)


class EstimatorClient:
    """One blimp's view of the service."""

    def __init__(
        self, session: zenoh.Session, blimp: str, timeout: float = 10.0, *, stream: bool = False
    ) -> None:
        self.session, self.blimp, self.timeout = session, blimp, timeout
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
                keys.blimp_key(self.blimp, kind), timeout=self.timeout
            )
        handler = querier.get(payload=payload, encoding=MSGPACK)
        try:  # the first reply is the answer: no wait for the query's final message
            r = handler.recv()
        except zenoh.ZError:  # closed without a reply
            msg = f"no reply to {kind} for blimp {self.blimp!r} within {self.timeout} s"
            raise ServiceError(msg) from None
        if r.ok is None:
            raw_err = r.err.payload.to_bytes()
            try:
                text = decode(raw_err).get("error", "unknown error")
            except ValueError:
                text = raw_err.decode("utf-8", "replace")  # zenoh's own errors, e.g. Timeout
            raise ServiceError(f"{kind} for blimp {self.blimp!r}: {text}")
        body = r.ok.payload.to_bytes()
        return decode_belief(body) if kind in ("step", "reset") else decode(body)

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
        return self.query("step", msg)

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
