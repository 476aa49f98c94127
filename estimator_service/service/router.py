"""``gpbf router``: a zenoh router for a fleet of estimator services and their clients.

No ``zenohd`` binary comes from the package registries here, so this is a zenoh session in
router mode: services (``gpbf serve --connect tcp/HOST:PORT``) and clients
(``open_session(["tcp/HOST:PORT"])``) on one or several machines meet through it; routers on
several machines join with ``--connect`` (``docs/deployment.md``). Multicast scouting stays
off; ``--zenoh-config`` is merged as for the service. A router announces the service's short
link lease (``SERVICE_LEASE_MS``, 2 s; a configuration file's own lease wins, except one equal
to zenoh's default of 10 s, which cannot be told from none), so a host that
vanishes is dropped by the other routers, and its services' blimps move, within it.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import zenoh

from estimator_service.cli_args import Parser
from estimator_service.service.config import (
    DEFAULT_ENDPOINT,
    SERVICE_LEASE_MS,
    describe,
    serve_until_stopped,
    zenoh_config,
    zenoh_message,
)

__all__ = ["main", "router_config"]


def router_config(
    listen: tuple[str, ...] = (DEFAULT_ENDPOINT,), file: Path | None = None, connect: tuple[str, ...] = ()
) -> zenoh.Config:
    """Router mode listening on ``listen`` (loopback by default) and connecting to the
    routers ``connect``, multicast scouting off, announcing the service's lease."""
    cfg = zenoh_config(listen=listen, connect=connect, file=file, lease_ms=SERVICE_LEASE_MS)
    unset = zenoh.Config().get_json("mode")
    if file is None or zenoh.Config.from_file(str(file)).get_json("mode") == unset:  # no mode chosen
        cfg.insert_json5("mode", '"router"')
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    return cfg


def main(argv: list[str] | None = None) -> int:
    p = Parser(prog="gpbf router", description=__doc__)
    p.add_argument(
        "--listen", action="append", default=None, help=f"endpoint (repeatable; none: {DEFAULT_ENDPOINT})"
    )
    p.add_argument("--connect", action="append", default=None, help="another router's endpoint (repeatable)")
    p.add_argument(
        "--zenoh-config", type=Path, default=None, help="JSON5 zenoh config merged onto the defaults"
    )
    args = p.parse_args(argv)
    try:
        cfg = router_config(
            tuple(args.listen or (DEFAULT_ENDPOINT,)), args.zenoh_config, tuple(args.connect or ())
        )
    except (ValueError, zenoh.ZError) as exc:
        print(f"gpbf router: error: {zenoh_message(exc)}", file=sys.stderr)
        return 2
    try:
        session = zenoh.open(cfg)
    except zenoh.ZError as exc:  # e.g. a port out of range, a host that does not resolve
        print(f"gpbf router: error: {zenoh_message(exc)} ({describe(cfg)})", file=sys.stderr)
        return 2
    return serve_until_stopped("gpbf router", describe(cfg), session.close)
