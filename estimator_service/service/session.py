"""One blimp's estimator session: its belief and input queue.

Zenoh callbacks only enqueue; a worker of the shared pool
(:mod:`estimator_service.service.workers`) decodes, validates and filters, so filtering
never runs in a zenoh thread. A message that fails validation, arrives late (older than
the session's time) or makes the filter fail is rejected and counted, and the belief
stays as it was.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from estimator_service.filters import GaussianBelief, StepInfo
from estimator_service.filters.common import finite
from estimator_service.filters.policy import batchable, step_one, update_many
from estimator_service.service import keys
from estimator_service.service.inbox import BATCH, ByteMeter, Inbox, Job
from estimator_service.service.limits import CatchUpBudget, ControlLog, Limits, gate_for, gated_step
from estimator_service.service.protocol import (
    MSGPACK,
    PROTOCOL_VERSION,
    ProtocolError,
    RepeatedStep,
    decode,
    encode,
    encode_belief,
    parse_camera,
    parse_control,
    parse_reset,
    parse_step,
)
from estimator_service.service.workers import WorkerPool
from estimator_service.system import System

__all__ = ["Session", "SessionSettings"]


@dataclass(frozen=True)
class SessionSettings:
    """Shared by all sessions of a service: the system the models describe (its ``dt``,
    sensor layout, control and state sizes, and the prior of a new session)."""

    system: System
    limits: Limits = field(default_factory=Limits)
    catch_up: CatchUpBudget | None = None  # the service's and tenants' catch-up work (None: unbounded)
    queued: ByteMeter | None = None  # payload bytes queued over all sessions (None: no service-wide cap)


@dataclass
class _NisMean:
    """The running mean of a session's NIS/dof since its reset, with the variance of that
    mean for a consistent filter (one update's NIS/dof has variance ``2 / dof``)."""

    total: float = 0.0
    count: int = 0
    var_sum: float = 0.0

    def add(self, nis: float, dof: int) -> None:
        self.total += nis / dof
        self.count += 1
        self.var_sum += 2.0 / dof

    def mean(self) -> float | None:
        return self.total / self.count if self.count else None

    def band(self) -> list[float] | None:
        """The 95 % band a consistent filter's mean falls in after these updates
        (:func:`~estimator_service.tracking.consistency_band`); None before one."""
        from estimator_service.tracking import consistency_band

        return list(consistency_band(1.0, self.var_sum / self.count**2)) if self.count else None


@dataclass
class _CatchUp:
    """A camera frame's predictions in progress across worker turns (nothing adopted yet)."""

    frame: Any
    belief: Any
    info: StepInfo
    n: int  # predictions to the frame's time
    known: bool  # the catch-up was reserved before any work
    reserved: float  # seconds reserved from the service's catch-up budget
    done: int = 0  # predictions made
    spent: float = 0.0  # seconds of catch-up predictions (those beyond the first)
    first_s: float = 0.0  # seconds of the first prediction (the catch-up's estimate before one is known)
    work: float = 0.0  # seconds of work in the earlier turns


@dataclass
class Session:
    """State and worker of one blimp.

    ``make_filter(filter_name, model_name)`` returns a (shared, immutable) filter;
    ``publish(kind, payload)`` sends ``belief`` or ``error`` messages.
    """

    blimp: str
    filter_name: str
    model_name: str
    settings: SessionSettings
    make_filter: Callable[[str, str], Any]
    publish: Callable[[str, bytes], None]
    model_version: str = ""
    service_id: str = ""
    seed: int = 0
    steps: int = 0
    rejected: int = 0
    late: int = 0
    batched: int = 0
    gated: int = 0
    refused_catch_up: int = 0  # camera frames refused for the service's catch-up budget
    t: float | None = None
    pool: WorkerPool | None = None
    _timings: deque = field(default_factory=lambda: deque(maxlen=1000))
    _nis: _NisMean = field(default_factory=_NisMean)
    _step_s: float = 0.0  # this session's measured seconds per prediction step (0: not yet)
    _last_step: tuple[int, float, bytes] | None = None  # (seq, t, reply) of the last step answered
    repeated: int = 0  # step queries answered again from the last reply (clients' retries)
    _yielded: bool = False  # the job just run gave the worker back (a catch-up in slices)

    def __post_init__(self) -> None:
        self._filter = self.make_filter(self.filter_name, self.model_name)
        self._controls = ControlLog(self.settings.limits.max_controls, self.settings.system.control_dim)
        lim = self.settings.limits
        self._inbox = Inbox(lim.queue_cap, self._dropped, lim.queue_bytes, self.settings.queued)
        sys_ = self.settings.system
        prior = GaussianBelief(np.array(sys_.prior_mean), np.diag(np.square(sys_.prior_std)))
        self._install(prior, self.seed)
        self._own_pool = self.pool is None
        if self.pool is None:
            from estimator_service.service.batching import step_together

            self.pool = WorkerPool(1, step_together)

    # -- called from zenoh callbacks: enqueue only --------------------------------------------
    def submit(self, kind: str, payload: bytes, query: Any = None, extra: Any = None) -> None:
        """Queue an input; at the queue cap the oldest pending one is dropped (O(1))."""
        if self._inbox.put((kind, payload, query, extra)):
            self.pool.schedule(self)

    def _dropped(self, job: Job) -> None:
        if isinstance(job[3], _CatchUp):  # a catch-up dropped mid-way: refund what it left
            self._settle(job[3])
        if job[2] is not None:
            lim = self.settings.limits
            text = (f"queue full (a session holds {lim.queue_cap} inputs and {lim.queue_bytes} bytes, "
                    f"the service {lim.total_queue_bytes} bytes): dropped")  # fmt: skip
            job[2].reply_err(self._error(text, job[0]), encoding=MSGPACK)
            job[2].drop()

    @property
    def dropped(self) -> int:
        """Inputs dropped because the queue was full."""
        return self._inbox.dropped

    @property
    def queue_bytes(self) -> int:
        """Payload bytes of the inputs pending now."""
        return self._inbox.bytes

    def idle_s(self, now: float | None = None) -> float:
        """Seconds since the last input; 0 while inputs are pending."""
        return self._inbox.idle_s(now)

    def stop(self) -> None:
        if self._own_pool:
            self.pool.stop()

    # -- what the worker pool calls (see WorkerPool) ---------------------------------------------
    @property
    def batch_key(self) -> int | None:
        """Sessions with the same key can be stepped in one batched call (None: cannot)."""
        return id(self._filter) if batchable(self._filter) else None

    def drain(self) -> None:
        """Run up to :data:`~estimator_service.service.inbox.BATCH` pending inputs (one
        worker at a time), then go back on the ready queue if more wait."""
        for _ in range(BATCH):
            if (job := self._inbox.take()) is None:
                return
            self.answer(job, lambda job=job: self.handle(job))
            self.close_job(job)
            if self._yielded:  # a catch-up gave the worker back: the others' turn
                self._yielded = False
                break
        self._reschedule()

    def head_step(self) -> Job | None:
        """Take the next input if it is a lock-step ``step`` (to batch it), else None."""
        return self._inbox.take_step()

    def close_job(self, job: Job) -> None:
        """Release a served job's query."""
        if job[2] is not None:
            job[2].drop()

    def _reschedule(self) -> None:
        """After a worker's turn: back on the ready queue if more inputs wait."""
        if self._inbox.again():
            self.pool.schedule(self)

    def finish(self, job: Job) -> None:
        """After a batched job: release its query; back on the ready queue if more wait."""
        self.close_job(job)
        self._reschedule()

    def answer(self, job: Job, compute: Callable[[], bytes | None]) -> None:
        """Reply to ``job``'s query (if any) with ``compute()``, or reject the input."""
        kind, _, query, _ = job
        try:
            reply = compute()
            if reply is None and kind == "camera":  # a catch-up continues on a later turn
                return
            if query is not None:
                query.reply(query.key_expr, reply, encoding=MSGPACK)
            if kind in ("step", "camera"):  # after the reply: the lock-step caller waits less
                self.publish("belief", reply)
        except RepeatedStep as rep:  # a retried query: the same reply, the belief not published again
            if query is not None:
                query.reply(query.key_expr, rep.reply, encoding=MSGPACK)
        except ProtocolError as exc:
            self.reject(str(exc), kind, query)
        except Exception as exc:  # a filter failure must not kill the session
            self.reject(f"{type(exc).__name__}: {exc}", kind, query)

    def _error(self, text: str, kind: str) -> bytes:
        return encode({"v": PROTOCOL_VERSION, "blimp": self.blimp, "input": kind, "error": text})

    def reject(self, text: str, kind: str, query: Any) -> None:
        self.rejected += 1
        msg = self._error(text, kind)
        self.publish("error", msg)
        if query is not None:
            query.reply_err(msg, encoding=MSGPACK)

    def handle(self, job: Job) -> bytes | None:
        """Serve one input: the reply (a belief or status message) or None (a control)."""
        kind, payload, _, extra = job
        if kind == "status":
            return self._status()
        if kind == "step":
            return self._step(payload)
        if isinstance(extra, _CatchUp):  # a camera frame's catch-up, continued
            return self._camera(extra.frame, extra)
        msg = decode(payload)
        if kind == "reset":
            return self._reset(parse_reset(msg, self.settings.system.state_dim))
        if kind == "control":
            c = parse_control(msg, self.settings.system.control_dim)
            self._check_time(c.t)
            self._controls.add(c.t, c.u)
            return None
        if kind == "camera":
            return self._camera(parse_camera(msg, extra, self._sizes))
        raise ProtocolError(f"unknown input {kind!r}")

    def _check_time(self, t: float) -> None:
        if self.t is not None and t < self.t - 1e-9:
            self.late += 1
            raise ProtocolError(
                f"field 't': {t} is older than the session time {self.t} (late or out of order)"
            )
        self._check_horizon(t)

    def _check_horizon(self, t: float) -> None:
        """Bound the predictions one input can cost: ``horizon_s`` and ``max_gap_steps`` of ``dt``."""
        horizon = min(
            self.settings.limits.horizon_s, self.settings.limits.max_gap_steps * self.settings.system.dt
        )
        if self.t is not None and t - self.t > horizon:
            raise ProtocolError(
                f"field 't': {t} is {t - self.t:.6g} s after the session time {self.t}, beyond the "
                f"service's horizon of {horizon:g} s; send a reset to re-synchronise"
            )

    # -- filtering ---------------------------------------------------------------------------------
    @property
    def _sizes(self) -> list[int]:
        return [sen.size for sen in self.settings.system.sensors]

    def _install(self, belief: GaussianBelief, seed: int) -> None:
        self._rng = np.random.default_rng(seed)
        self._belief = self._filter.initial(belief, self._rng)
        self._last_step = None  # a step from before a reset is never answered again

    def _commit(self, belief, info: StepInfo, seq: int, t: float, t0: float) -> bytes:
        """Adopt the new belief (only after everything succeeded) and encode it (the caller
        replies with it and publishes it)."""
        g = self._filter.gaussian(belief)
        if not finite(g.mean, g.cov):
            raise ProtocolError("filter produced a non-finite belief; input rejected")
        self._belief, self.t = belief, t
        self.steps += 1
        if info.dof > 0 and math.isfinite(info.nis):
            self._nis.add(info.nis, info.dof)
        ms = (time.perf_counter() - t0) * 1e3
        self._timings.append(ms)
        return self._message(g, seq, t, info, ms)

    def _message(self, g: GaussianBelief, seq: int, t: float, info: StepInfo, ms: float) -> bytes:
        return encode_belief(
            self.blimp, seq, t, g.mean, g.cov, self.filter_name, self.model_name,
            info.nis, info.dof, info.diverged, ms, service=self.service_id,
        )  # fmt: skip

    def commit_batched(self, step: Any, belief: Any, info: StepInfo, t0: float, together: int) -> bytes:
        """:meth:`_commit` for a step computed in a batch of ``together`` sessions."""
        self.gated += info.gated  # refused by the gate: the belief is the prediction
        self.batched += together > 1
        return self._remember(self._commit(belief, info, step.seq, step.t, t0), step.seq, step.t)

    @property
    def filter(self) -> Any:
        """The session's (shared, immutable) filter."""
        return self._filter

    @property
    def belief(self) -> Any:
        """The current belief, in the filter's own form."""
        return self._belief

    def prepare_step(self, payload: bytes) -> tuple[Any, np.ndarray, np.ndarray]:
        """Decode and check a ``step`` input: the parsed step, ``z`` and ``valid``."""
        s = parse_step(decode(payload), self._sizes, self.settings.system.control_dim)
        last = self._last_step
        if last is not None and (s.seq, s.t) == last[:2] and s.t == self.t:
            self.repeated += 1
            raise RepeatedStep(last[2])
        if self.t is not None and s.t <= self.t:
            self.late += 1
            raise ProtocolError(f"field 't': step time {s.t} is not after the session time {self.t}")
        self._check_horizon(s.t)
        z, valid = self.settings.system.frames(s.frames)
        return s, z, valid

    def _step(self, payload: bytes) -> bytes:
        t0 = time.perf_counter()
        s, z, valid = self.prepare_step(payload)
        belief, info = gated_step(
            self._filter, self._belief, s.u, z, valid, self._rng, self.settings.limits.gate_p
        )
        self.gated += info.gated
        return self._remember(self._commit(belief, info, s.seq, s.t, t0), s.seq, s.t)

    def _remember(self, reply: bytes, seq: int, t: float) -> bytes:
        """Keep a step's reply for a retried query (:class:`RepeatedStep`)."""
        self._last_step = (seq, t, reply)
        return reply

    def _camera(self, c, cont: _CatchUp | None = None) -> bytes | None:
        """A camera frame: predict to its time with the controls then in force, read it at
        the last step. A catch-up yields the worker every ``catch_up_slice_s`` of work (its
        predictions so far kept aside, nothing adopted) and continues on the session's next
        turn, so other blimps' steps wait at most a slice or one prediction, whichever is
        longer (a particle filter's prediction can take longer than a slice); None until it
        has finished."""
        turn = time.perf_counter()
        if cont is None:
            self._check_time(c.t)
            n = 0 if self.t is None else round((c.t - self.t) / self.settings.system.dt)
            known = n > 1 and self._step_s > 0  # the step time is known: refuse a catch-up before any work
            reserved = self._reserve_catch_up(n - 1, self._step_s) if known else 0.0
            cont = _CatchUp(c, self._belief, StepInfo(), n, known, reserved)
        dt, delay = self.settings.system.dt, self.settings.system.control_delay  # a command acts `delay` late
        z, valid = self.settings.system.frames({} if c.ellipse is None else {c.camera: c.ellipse})
        gate, none = gate_for(self.settings.limits.gate_p), np.zeros_like(valid)
        clock = time.perf_counter()
        try:
            for i in range(cont.done, cont.n):  # read at the last step
                if i == 1:  # beyond the first step: catching up, within the service's budget
                    if not cont.known:
                        cont.reserved = self._reserve_catch_up(cont.n - 1, cont.first_s)
                    clock = time.perf_counter()
                u = self._control_at(self.t + i * dt - delay)
                read = valid if i == cont.n - 1 else none
                cont.belief, cont.info = step_one(self._filter, cont.belief, u, z, read, self._rng, gate)
                cont.done = i + 1
                if i == 0:
                    cont.first_s = time.perf_counter() - clock
                if cont.done < cont.n and time.perf_counter() - turn >= self.settings.limits.catch_up_slice_s:
                    cont.spent += time.perf_counter() - clock if i >= 1 else 0.0
                    cont.work += time.perf_counter() - turn
                    self._inbox.put_front(("camera", b"", None, cont))  # the rest on the next turn
                    self._yielded = True
                    return None
        except Exception:  # the frame is rejected: what the catch-up reserved and did not spend comes back
            cont.spent += time.perf_counter() - clock if cont.done > 1 else 0.0
            self._settle(cont)
            raise
        if cont.n > 1:
            cont.spent += time.perf_counter() - clock
        if cont.reserved:
            self._step_s = 0.5 * self._step_s + 0.5 * cont.spent / (cont.n - 1)
        self._settle(cont)
        belief, info = cont.belief, cont.info
        if cont.n == 0:  # a frame at the belief's own time: the update alone
            belief, info = update_many(self._filter, [belief], z[None], valid[None], gate, self._rng)[0]
        self.gated += info.gated
        return self._commit(belief, info, c.seq, c.t, turn - cont.work)

    def _settle(self, cont: _CatchUp) -> None:
        """Replace what ``cont`` reserved from the service's catch-up budget by what it spent
        (once: at its end, its failure, or its drop at the queue cap)."""
        if cont.reserved:
            self.settings.catch_up.settle(keys.tenant(self.blimp), cont.reserved, cont.spent)
            cont.reserved = 0.0

    def _reserve_catch_up(self, steps: int, first_s: float) -> float:
        """Reserve ``steps`` predictions of catch-up work (estimated from this session's step
        time; the first step's ``first_s`` before there is one) from the service's budget, or
        refuse the input (nothing adopted, no state changed)."""
        budget = self.settings.catch_up
        if budget is None:
            return 0.0
        self._step_s = self._step_s or first_s
        estimate = steps * self._step_s
        refused = budget.take(keys.tenant(self.blimp), estimate)
        if refused is not None:
            self.refused_catch_up += 1
            raise ProtocolError(
                f"field 't': catching up {steps} steps would take about {estimate:.3g} s of filtering; "
                f"{refused}; send frames as they come, or a reset"
            )
        return estimate

    def _control_at(self, t: float) -> np.ndarray:
        """The latest control at or before ``t``; older ones are forgotten."""
        u = self._controls.at(t)
        self._controls.forget_before(t)
        return u

    def _reset(self, r) -> bytes:
        if r.filter or r.model:
            self.filter_name, self.model_name = r.filter or self.filter_name, r.model or self.model_name
            self._filter = self.make_filter(self.filter_name, self.model_name)
            self._step_s = 0.0  # another filter: its step time is measured afresh
        self._install(GaussianBelief(r.mean, r.cov), r.seed)
        self.t, self.steps, self._nis = r.t, 0, _NisMean()
        self._controls.clear()
        return self._message(self._filter.gaussian(self._belief), r.seq, r.t, StepInfo(), 0.0)

    def _status(self) -> bytes:
        ms = np.array(self._timings) if self._timings else np.zeros(1)
        return encode({
            "v": PROTOCOL_VERSION, "blimp": self.blimp, "filter": self.filter_name, "model": self.model_name,
            "model_version": self.model_version, "steps": self.steps, "rejected": self.rejected,
            "late": self.late, "dropped": self.dropped, "gated": self.gated,
            "refused_catch_up": self.refused_catch_up, "repeated": self.repeated,
            "nis_per_dof_mean": self._nis.mean(), "nis_per_dof_band": self._nis.band(),
            "batched": self.batched, "t": self.t, "queue": len(self._inbox),
            "timings": {"count": len(self._timings), "step_ms_p50": float(np.median(ms)),
                        "step_ms_p99": float(np.percentile(ms, 99))},
        })  # fmt: skip
