"""A bare zenoh queryable for ``bench_service``: the transport floor on this machine.

``python benchmarks/zenoh_echo.py PORT WORK_S [STREAM_MB]`` replies to ``echo/**`` with a
1.5 kB payload (a belief's size) from a worker thread (the same hand-off as the service).
The work stands in for the filter step: with ``STREAM_MB``, one pass over a buffer of that
size (as an exact GP's step reads its Cholesky factors once, evicting the caches the
transport then runs from), then spinning until ``WORK_S`` seconds have passed. The reply
starts with the seconds the work took; round trip minus that is what zenoh, Python and the
machine cost with no protocol, parsing or filter.
"""

from __future__ import annotations

import queue
import sys
import threading
import time

import numpy as np
import zenoh


def main() -> None:
    port, work = int(sys.argv[1]), float(sys.argv[2])
    stream_mb = float(sys.argv[3]) if len(sys.argv) > 3 else 0.0
    cfg = zenoh.Config()
    cfg.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(cfg)
    jobs: queue.SimpleQueue = queue.SimpleQueue()
    rows = max(1, int(stream_mb * 2**20 / 8192))
    buf, ones = (np.ones((rows, 1024)), np.ones(1024)) if stream_mb > 0 else (None, None)

    def worker() -> None:
        while True:
            q = jobs.get()
            t0 = time.perf_counter()
            if buf is not None:  # one pass over the buffer, 1 MB at a time
                for i in range(0, rows, 128):
                    buf[i : i + 128] @ ones
            while time.perf_counter() - t0 < work:
                pass
            done = time.perf_counter() - t0  # the work as done (a pass may outlast WORK_S)
            q.reply(q.key_expr, f"{done:.9f}".encode().ljust(1500))
            q.drop()

    threading.Thread(target=worker, daemon=True).start()
    _q = session.declare_queryable("echo/**", jobs.put)
    print("ready", flush=True)
    sys.stdin.read()  # until the parent closes our stdin
    session.close()


if __name__ == "__main__":
    main()
