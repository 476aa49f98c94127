"""A bare zenoh queryable for ``bench_service``: the transport floor on this machine.

``python benchmarks/zenoh_echo.py PORT WORK_S [STREAM_MB]`` replies to ``echo/**`` with a
1.5 kB payload (a belief's size) from a worker thread (the same hand-off as the service),
after ``WORK_S`` seconds standing in for the filter step: spinning, or, with
``STREAM_MB``, reading a buffer of that size over and over as an exact GP's step reads its
Cholesky factors (which evicts the caches the transport then runs from). Round trip minus
``WORK_S`` is what zenoh, Python and the machine cost with no protocol, parsing or filter.
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
            t0, i = time.perf_counter(), 0
            while time.perf_counter() - t0 < work:
                if buf is not None:  # 1 MB at a time, cycling through the buffer
                    buf[i : i + 128] @ ones
                    i = (i + 128) % rows
            q.reply(q.key_expr, b"x" * 1500)
            q.drop()

    threading.Thread(target=worker, daemon=True).start()
    _q = session.declare_queryable("echo/**", jobs.put)
    print("ready", flush=True)
    sys.stdin.read()  # until the parent closes our stdin
    session.close()


if __name__ == "__main__":
    main()
