"""The service's zenoh key expressions: the one owner of every key string.

``gpbf/<blimp>/<kind>`` for a blimp's inputs (``control``, ``camera/<k>``), outputs
(``belief``, ``error``) and queries (``step``, ``reset``, ``status``); a liveliness token
``gpbf/@service/<id>`` per running service. A blimp id ``<tenant>.<name>`` names the tenant
whose session quota it counts against (an access-control rule on ``gpbf/<tenant>.$*/...``
binds a tenant to a logged-in identity). ``docs/protocol.md`` documents them.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterable

__all__ = [
    "BLIMP_ID",
    "BLIMP_ID_RULE",
    "INPUTS",
    "LIVELINESS_PREFIX",
    "OUTPUTS",
    "PREFIX",
    "QUERIES",
    "SERVICE_ID",
    "blimp_key",
    "camera_key",
    "hello_key",
    "liveliness_key",
    "owner",
    "parse_key",
    "sessions_key",
    "tenant",
    "wildcard",
]

PREFIX = "gpbf"
LIVELINESS_PREFIX = f"{PREFIX}/@service"
TENANT_SEP = "."
_NAME = r"[A-Za-z0-9_\-]{1,64}"
#: a service id: one name (use ``fullmatch``: ``$`` would let a trailing newline through)
SERVICE_ID = re.compile(_NAME)
#: a blimp id: a name, or ``<tenant>.<name>`` (``fullmatch``)
BLIMP_ID = re.compile(rf"(?:{_NAME}{re.escape(TENANT_SEP)})?{_NAME}")
BLIMP_ID_RULE = f"invalid blimp id: [<tenant>{TENANT_SEP}]<name>, each 1-64 characters of A-Z a-z 0-9 _ -"
INPUTS = ("control", "camera")
OUTPUTS = ("belief", "error")
QUERIES = ("step", "reset", "status", "close")


def blimp_key(blimp: str, kind: str) -> str:
    """``gpbf/<blimp>/<kind>``."""
    return f"{PREFIX}/{blimp}/{kind}"


def camera_key(blimp: str, camera: int) -> str:
    """``gpbf/<blimp>/camera/<k>``."""
    return f"{PREFIX}/{blimp}/camera/{camera}"


def wildcard(kind: str) -> str:
    """The key expression that matches ``kind`` for every blimp (``camera``: every camera)."""
    return f"{PREFIX}/*/camera/*" if kind == "camera" else f"{PREFIX}/*/{kind}"


def tenant(blimp: str) -> str:
    """The tenant of a blimp id: its part before ``.``; ``""`` (the shared tenant) without one."""
    head, sep, _ = blimp.partition(TENANT_SEP)
    return head if sep else ""


def liveliness_key(service_id: str) -> str:
    return f"{LIVELINESS_PREFIX}/{service_id}"


def hello_key(service_id: str) -> str:
    """``gpbf/@service/<id>/hello``: the query a service answers to be admitted to a fleet
    (:mod:`estimator_service.service.membership`)."""
    return f"{LIVELINESS_PREFIX}/{service_id}/hello"


def sessions_key(service_id: str) -> str:
    """``gpbf/@service/<id>/sessions``: the query that lists a service's sessions (``*``: all)."""
    return f"{LIVELINESS_PREFIX}/{service_id}/sessions"


def owner(blimp: str, services: Iterable[str]) -> str | None:
    """The service that owns ``blimp`` among the live ``services`` (rendezvous hashing: each
    blimp goes to the service with the highest ``sha256(service/blimp)``, so when a service
    joins or leaves only the blimps it takes or held move). None when there is none."""
    return max(services, key=lambda s: hashlib.sha256(f"{s}/{blimp}".encode()).digest(), default=None)


def parse_key(key: str) -> tuple[str | None, str, int | None]:
    """``(blimp or None when invalid, kind, camera index)`` of a received key; the camera
    index is -1 for a camera key whose last part is not ASCII digits, None elsewhere."""
    parts = key.split("/")
    blimp = parts[1] if len(parts) >= 3 else ""
    kind = parts[2] if len(parts) >= 3 else ""
    camera = None
    if kind == "camera":
        last = parts[3] if len(parts) == 4 else ""
        camera = int(last) if last.isascii() and last.isdigit() and len(last) <= 6 else -1
    return (blimp if BLIMP_ID.fullmatch(blimp) else None), kind, camera
