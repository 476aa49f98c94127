"""Fleet membership that a liveliness token alone cannot obtain.

A service announces itself with a liveliness token ``gpbf/@service/<id>`` and answers the
query ``gpbf/@service/<id>/hello`` with ``{"v": protocol, "service": <id>, "hello": true}``.
Another service admits it to the fleet (and so hands it the blimps it now owns) only after
that answer: a peer that merely declares tokens, however many, never becomes a member, so
it can make no real service drop, refuse or forget a blimp. Until admitted a token is
*pending* (at most :data:`MAX_PENDING` at a time; beyond that, and after
:data:`HELLO_TRIES` unanswered queries, it is counted as refused). Where the zenoh network
authenticates its peers, the access control should also let only service identities declare
tokens and queryables under ``gpbf/@service/**`` (``docs/examples/secure/service.json5``):
without authentication a determined stranger can still run something that answers.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import zenoh

from estimator_service.service import keys
from estimator_service.service.protocol import PROTOCOL_VERSION, decode, encode

__all__ = ["HELLO_TIMEOUT_S", "HELLO_TRIES", "MAX_HELLO_BYTES", "MAX_PENDING", "Membership"]

HELLO_TIMEOUT_S = 1.0  # how long one hello query waits for its answer
HELLO_TRIES = 3  # hello queries before a token counts as refused (a peer's queryable may arrive late)
MAX_PENDING = 64  # tokens being verified at once; more are refused at once (a flood costs nothing)
MAX_HELLO_BYTES = 1024  # a longer answer is not a service's


class Membership:
    """The fleet as one service sees it: itself and the services that answered its hello.

    ``on_change(live)`` runs (under ``lock``) whenever the set of members changes.
    """

    def __init__(
        self, session: zenoh.Session, me: str, lock: threading.RLock,
        on_change: Callable[[frozenset[str]], None],
    ) -> None:  # fmt: skip
        self._session, self.me, self._lock, self._on_change = session, me, lock, on_change
        self.live: frozenset[str] = frozenset({me})
        self._pending: dict[str, int] = {}  # service -> hello queries left
        self.refused = 0  # tokens that never answered as a service (or came while too many were pending)

    @property
    def pending(self) -> int:
        with self._lock:
            return len(self._pending)

    def hello(self) -> bytes:
        """This service's answer to its hello query."""
        return encode({"v": PROTOCOL_VERSION, "service": self.me, "hello": True})

    def on_token(self, sample: zenoh.Sample) -> None:
        """A liveliness token appeared or went: verify a newcomer; forget a member that left."""
        service = str(sample.key_expr).rsplit("/", 1)[-1]
        if service == self.me:
            return
        if sample.kind != zenoh.SampleKind.PUT:
            with self._lock:
                self._pending.pop(service, None)
                if service in self.live:
                    self._set(self.live - {service})
            return
        with self._lock:
            if service in self.live or service in self._pending:
                return
            if not keys.SERVICE_ID.fullmatch(service) or len(self._pending) >= MAX_PENDING:
                self.refused += 1
                return
            self._pending[service] = HELLO_TRIES
        self._ask(service)

    def _set(self, live: frozenset[str]) -> None:
        self.live = live
        self._on_change(live)

    def _ask(self, service: str) -> None:
        handler = zenoh.handlers.Callback(
            lambda reply: self._answered(service, reply), lambda: self._ended(service)
        )
        try:
            self._session.get(keys.hello_key(service), handler, timeout=HELLO_TIMEOUT_S)
        except zenoh.ZError:  # the session is closing
            with self._lock:
                self._pending.pop(service, None)

    def _answered(self, service: str, reply: zenoh.Reply) -> None:
        ok = reply.ok
        if ok is None or len(ok.payload) > MAX_HELLO_BYTES:
            return
        try:
            msg = decode(ok.payload.to_bytes())
        except Exception:
            return
        if not (isinstance(msg, dict) and msg.get("hello") is True and msg.get("service") == service
                and msg.get("v") == PROTOCOL_VERSION):  # fmt: skip
            return
        with self._lock:
            if self._pending.pop(service, None) is not None:
                self._set(self.live | {service})

    def _ended(self, service: str) -> None:
        """A hello query finished: ask again while tries are left, else count a refusal."""
        with self._lock:
            left = self._pending.get(service)
            if left is None:  # admitted, or its token went
                return
            if left <= 1:
                del self._pending[service]
                self.refused += 1
                return
            self._pending[service] = left - 1
        threading.Timer(0.1, self._ask, (service,)).start()  # not from zenoh's own callback thread
