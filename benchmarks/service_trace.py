"""``gpbf serve`` with timestamps on the lock-step path, for ``bench_service``.

``python benchmarks/service_trace.py OUT.json [serve options]`` runs the estimator service
unchanged except that, for every ``step`` query, it records ``time.perf_counter()`` (the
same monotonic clock in every process on the machine) when zenoh hands the query to the
service's callback, when a worker picks it up, when the step starts and ends, and when the
reply has been handed back to zenoh. On shutdown it writes them to ``OUT.json``, one
``[callback, worker, step_start, step_end, replied]`` row per step. The timestamps of the
query in flight share one slot, so drive it with one lock-step query at a time.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

from estimator_service.service import server, session

ROWS: list[list[float]] = []
NOW: dict[str, float] = {}


class _TimedQuery:
    """A query whose ``reply`` notes when zenoh has taken the reply."""

    def __init__(self, query: Any) -> None:
        self.query, self.key_expr = query, query.key_expr

    def reply(self, key: Any, payload: bytes, **kw: Any) -> None:
        self.query.reply(key, payload, **kw)
        NOW["replied"] = time.perf_counter()

    def reply_err(self, payload: bytes, **kw: Any) -> None:
        self.query.reply_err(payload, **kw)

    def drop(self) -> None:
        self.query.drop()


def _patch() -> None:
    on_query = server.EstimatorService._on_query
    answer, step = session.Session.answer, session.Session._step

    def timed_on_query(self, query) -> None:
        NOW["callback"] = time.perf_counter()
        on_query(self, query)

    def timed_answer(self, job, compute) -> None:
        NOW["worker"] = time.perf_counter()
        kind, payload, query, extra = job
        timed = kind == "step" and query is not None
        answer(self, (kind, payload, _TimedQuery(query) if timed else query, extra), compute)
        if timed:
            ROWS.append([NOW[k] for k in ("callback", "worker", "step_start", "step_end", "replied")])

    def timed_step(self, payload: bytes) -> bytes:
        NOW["step_start"] = time.perf_counter()
        out = step(self, payload)
        NOW["step_end"] = time.perf_counter()
        return out

    server.EstimatorService._on_query = timed_on_query
    session.Session.answer = timed_answer
    session.Session._step = timed_step


def main() -> int:
    out = Path(sys.argv[1])
    _patch()
    code = server.main(sys.argv[2:])
    out.write_text(json.dumps(ROWS))
    return code


if __name__ == "__main__":
    raise SystemExit(main())
