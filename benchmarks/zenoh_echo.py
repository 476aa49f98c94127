"""A bare zenoh queryable for ``bench_service``: the transport floor on this machine.

``python benchmarks/zenoh_echo.py PORT WORK_S`` replies to ``echo/**`` with a 1.5 kB
payload (a belief's size) from a worker thread (the same hand-off as the service), after
spinning ``WORK_S`` seconds (standing in for the filter step). Round trip minus
``WORK_S`` is what zenoh, Python and the machine cost with no protocol, parsing or filter.
"""

from __future__ import annotations

import queue
import sys
import threading
import time

import zenoh


def main() -> None:
    port, work = int(sys.argv[1]), float(sys.argv[2])
    cfg = zenoh.Config()
    cfg.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(cfg)
    jobs: queue.SimpleQueue = queue.SimpleQueue()

    def worker() -> None:
        while True:
            q = jobs.get()
            t0 = time.perf_counter()
            while time.perf_counter() - t0 < work:
                pass
            q.reply(q.key_expr, b"x" * 1500)
            q.drop()

    threading.Thread(target=worker, daemon=True).start()
    _q = session.declare_queryable("echo/**", jobs.put)
    print("ready", flush=True)
    sys.stdin.read()  # until the parent closes our stdin
    session.close()


if __name__ == "__main__":
    main()
