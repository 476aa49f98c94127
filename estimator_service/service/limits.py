"""What bounds the work and memory one message, one session and one service can cost.

Every limit is configuration (``gpbf serve`` options) and documented in
``docs/protocol.md``; the defaults are chosen so that normal use never meets them.
"""

from __future__ import annotations

import argparse
import bisect
import functools
import math
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from estimator_service.cli_args import checked_float, checked_int
from estimator_service.filters import StepInfo
from estimator_service.filters.policy import Gate, step_one
from estimator_service.service.config import SERVICE_LEASE_MS

__all__ = [
    "OPTIONS",
    "WATCH_TICK_S",
    "CatchUpBudget",
    "ControlLog",
    "Limits",
    "WorkBudget",
    "add_limit_options",
    "fence_and_tick",
    "gate_for",
    "gated",
    "gated_step",
    "limits_from",
]


@dataclass(frozen=True)
class Limits:
    """Service limits.

    Attributes
    ----------
    horizon_s
        An input whose time is more than this after its session's time is rejected (a
        camera frame there would make the session predict ``horizon_s / dt`` steps);
        re-synchronise with a ``reset``. 60 s is 240 blimp steps, about 0.5 s of work.
    max_gap_steps
        The same bound in filter steps: for a robot with a short ``dt`` the horizon is
        ``min(horizon_s, max_gap_steps * dt)``, so one input never costs more than this many
        predictions.
    queue_cap, queue_bytes
        Pending inputs and their payload bytes per session. Over either, the oldest pending
        input is dropped and counted (``dropped`` in ``status``; a dropped query gets an
        error reply).
    total_queue_bytes
        Payload bytes pending over all sessions of the service; an input that would pass
        it is dropped itself (and counted), so queues cannot exhaust the memory whatever the
        number of blimps.
    max_controls
        Streamed controls a session remembers (the latest ones); older ones are forgotten.
    gate_p
        Innovation gate: a sensor update whose NIS has a chi-square tail probability below
        ``gate_p`` is not applied (the prediction is kept, ``gated`` counts it), as
        robot_localization's Mahalanobis threshold; 0 turns the gate off.
    session_ttl_s
        A session without input for this long is closed (0: never).
    max_sessions
        Sessions per service; at the cap, expired sessions are closed first, otherwise a
        new blimp is refused with an error naming the cap.
    evict_idle_s
        At the session cap or its tenant's quota, a new blimp's reset closes a session idle
        this long (counted as ``evicted``): its own tenant's least recently used first, at
        the cap then the one idle the longest; otherwise the reset is refused.
    session_quota
        Sessions per tenant (:func:`~estimator_service.service.keys.tenant`: a blimp id's part
        before ``.``; ids without one share the tenant ``""``). A tenant's new blimp at its
        quota, or at the session cap, first closes that tenant's own least recently used
        session idle for ``evict_idle_s``; at the quota it is refused otherwise, naming the
        tenant. With ``max_sessions >= session_quota x tenants``, a tenant whose identity the
        access configuration binds to its ids (``gpbf/<tenant>.$*/...``) cannot lock others
        out, however many resets it sends. 0 (the default): no quota, so a service of one
        tenant keeps its whole table; an operator of several tenants sets it.
    fence_after_s
        A service whose own clock shows it was frozen (stopped, swapped out) for longer than
        this forgets every session on waking: the fleet may have given its blimps to others
        meanwhile, and their clients re-create each session from their last belief instead of
        meeting the stale one. Half the lease a service announces
        (:data:`~estimator_service.service.config.SERVICE_LEASE_MS`), after which the others
        see the frozen service gone; a service never waits longer than half the lease in
        effect (:func:`fence_and_tick`: a ``--zenoh-config`` with a shorter lease shortens it).
    catch_up_share, catch_up_burst_s
        Catching up, the predictions a camera frame needs beyond the first to reach its time,
        may use at most ``catch_up_share`` seconds of filtering per second over all sessions,
        with bursts up to ``catch_up_burst_s`` (:class:`WorkBudget`). A frame whose catch-up
        would cost more than is available (estimated from the session's own measured step
        time) is refused before any work, naming the limit: frames each just inside the
        horizon, from any number of blimps, cannot stall the others' steps for long. The burst
        is also the most one catch-up may cost (bursts of 0.05 s refused every streamed frame
        of a particle filter whose catch-up of a few steps costs more: 0.2-0.5 s per step on a
        900-point GP).
    tenant_catch_up_share
        The part of ``catch_up_share`` one tenant's frames may use (its own bucket, with
        bursts up to ``catch_up_burst_s``; the service's bucket holds ``catch_up_burst_s x
        catch_up_share / tenant_catch_up_share``: :class:`CatchUpBudget`): a tenant's
        near-horizon chains exhaust its own share and leave the rest to the others' catch-ups.
        0 (the default): no part of its own, a tenant may use the whole budget.
    catch_up_slice_s
        A catch-up gives its worker to the other sessions after this many seconds of work and
        continues on its session's next turn (its predictions kept aside, nothing adopted
        until the frame is read). Before, one catch-up held its worker to the end: a healthy
        GP-EKF blimp's step p99 was 270-311 ms over the 60 steps after near-horizon chains
        were sent to EKF and PF blimps (``bench_service`` ``near_horizon_healthy_p99_ms``).
    """

    horizon_s: float = 60.0
    max_gap_steps: int = 1000
    queue_cap: int = 1024
    queue_bytes: int = 4_000_000
    total_queue_bytes: int = 256 * 2**20
    max_controls: int = 256
    gate_p: float = 1e-9
    session_ttl_s: float = 600.0
    max_sessions: int = 4096
    evict_idle_s: float = 30.0
    session_quota: int = 0
    fence_after_s: float = SERVICE_LEASE_MS / 2000
    catch_up_share: float = 0.5
    catch_up_burst_s: float = 2.0
    tenant_catch_up_share: float = 0.0
    catch_up_slice_s: float = 0.02

    def __post_init__(self) -> None:
        checks = {
            "horizon_s": self.horizon_s > 0, "max_gap_steps": self.max_gap_steps >= 1,
            "queue_cap": self.queue_cap >= 1, "queue_bytes": self.queue_bytes >= 1,
            "total_queue_bytes": self.total_queue_bytes >= 1,
            "max_controls": self.max_controls >= 1, "gate_p": 0 <= self.gate_p < 1,
            "session_ttl_s": self.session_ttl_s >= 0,
            "max_sessions": self.max_sessions >= 1,
            "evict_idle_s": self.evict_idle_s >= 0, "session_quota": self.session_quota >= 0,
            "fence_after_s": self.fence_after_s > 0,
            "catch_up_share": self.catch_up_share > 0,
            "catch_up_burst_s": self.catch_up_burst_s > 0, "catch_up_slice_s": self.catch_up_slice_s > 0,
            "tenant_catch_up_share": self.tenant_catch_up_share >= 0
            and not self.tenant_catch_up_share > self.catch_up_share,  # a part of it
        }  # fmt: skip
        bad = [k for k, ok in checks.items() if not ok or not math.isfinite(getattr(self, k))]
        if bad:
            over = self.tenant_catch_up_share > self.catch_up_share  # a part larger than the whole
            part = f" (more than catch_up_share, {self.catch_up_share})" if over else ""
            why = {"tenant_catch_up_share": part}
            listed = ", ".join(f"{k}={getattr(self, k)}{why.get(k, '')}" for k in bad)
            raise ValueError(f"service limits out of range: {listed}")


#: ``gpbf serve`` option, :class:`Limits` field, parser type and help, one row per limit
OPTIONS = (
    ("--horizon", "horizon_s", checked_float(0.0, 1e6, low_open=True),
     "seconds an input may lie after its session's time (more: rejected; reset to re-sync)"),
    ("--max-gap-steps", "max_gap_steps", checked_int(1, 10**7),
     "filter steps an input may lie after its session's time (bounds one input's work)"),
    ("--queue-cap", "queue_cap", checked_int(1, 1_000_000),
     "pending inputs per session (over it the oldest is dropped and counted)"),
    ("--queue-bytes", "queue_bytes", checked_int(1, 2**40),
     "payload bytes pending per session (over it the oldest input is dropped and counted)"),
    ("--total-queue-bytes", "total_queue_bytes", checked_int(1, 2**40),
     "payload bytes pending over all sessions (an input over it is dropped and counted)"),
    ("--max-controls", "max_controls", checked_int(1, 1_000_000), "streamed controls a session remembers"),
    ("--gate-p", "gate_p", checked_float(0.0, 0.5),
     "innovation gate: skip an update whose NIS tail probability is below this (0: off)"),
    ("--session-ttl", "session_ttl_s", checked_float(0.0, 1e9),
     "seconds without input after which a session is closed (0: never)"),
    ("--max-sessions", "max_sessions", checked_int(1, 1_000_000), "sessions per service"),
    ("--evict-idle", "evict_idle_s", checked_float(0.0, 1e9),
     "seconds idle after which a session may be closed for a new blimp at the cap or its tenant's quota"),
    ("--session-quota", "session_quota", checked_int(0, 1_000_000),
     "sessions per tenant (a blimp id's part before '.'; ids without one share one tenant; 0: none)"),
    ("--fence-after", "fence_after_s", checked_float(0.0, 1e6, low_open=True),
     "seconds frozen after which a waking service forgets its sessions (its blimps may have moved)"),
    ("--catch-up-share", "catch_up_share", checked_float(0.0, 64.0, low_open=True),
     "seconds of catch-up predictions per second, over all sessions (frames beyond it: refused)"),
    ("--tenant-catch-up-share", "tenant_catch_up_share", checked_float(0.0, 64.0),
     "seconds of catch-up work per second one tenant's frames may use (of --catch-up-share; 0: all)"),
    ("--catch-up-burst", "catch_up_burst_s", checked_float(0.0, 3600.0, low_open=True),
     "seconds of catch-up predictions available at once"),
    ("--catch-up-slice", "catch_up_slice_s", checked_float(0.0, 60.0, low_open=True),
     "seconds of catch-up work a frame does before the worker serves other blimps (it resumes next turn)"),
)  # fmt: skip


#: the freeze watchdog's longest tick (shorter where the fence is short, see fence_and_tick)
WATCH_TICK_S = 0.25
#: the shortest fence, whatever the lease (a lease of 0 would make the watchdog spin)
MIN_FENCE_S = 0.05


def fence_and_tick(fence_after_s: float, lease_s: float) -> tuple[float, float]:
    """The freeze fence a service applies and its watchdog's tick: ``fence_after_s``, but at
    most half the link lease in effect ``lease_s`` (the others drop a frozen service after
    the lease, so its blimps may have moved) and at least :data:`MIN_FENCE_S`, and a tick of
    at most a quarter of the fence so that a healthy watchdog's late tick never looks like a
    freeze."""
    fence = max(min(fence_after_s, lease_s / 2.0), MIN_FENCE_S)
    return fence, min(WATCH_TICK_S, fence / 4.0)


class WorkBudget:
    """A token bucket of filtering seconds: ``rate`` seconds per second, at most ``burst``
    at once; thread-safe. :meth:`take` reserves an estimate before work, :meth:`settle`
    replaces it by what the work cost."""

    def __init__(self, rate: float, burst: float, clock=time.monotonic) -> None:
        self.rate, self.burst, self._clock = rate, burst, clock
        self._tokens, self._at = burst, clock()
        self._lock = threading.Lock()
        self.refused = 0

    def take(self, estimate_s: float) -> float | None:
        """Reserve ``estimate_s``; None (and counted) when only less is available; else what
        remains."""
        with self._lock:
            now = self._clock()
            self._tokens = min(self.burst, self._tokens + (now - self._at) * self.rate)
            self._at = now
            if estimate_s > self._tokens:
                self.refused += 1
                return None
            self._tokens -= estimate_s
            return self._tokens

    def available(self) -> float:
        with self._lock:
            return min(self.burst, self._tokens + (self._clock() - self._at) * self.rate)

    def settle(self, estimate_s: float, actual_s: float) -> None:
        """The work reserved at ``estimate_s`` cost ``actual_s``."""
        with self._lock:
            self._tokens = min(self.burst, self._tokens + estimate_s - actual_s)


class CatchUpBudget:
    """The service's catch-up budget and each tenant's own part of it (thread-safe): a
    reservation must fit both the tenant's :class:`WorkBudget` (``tenant_rate`` seconds per
    second, at most ``burst`` at once: the most one catch-up may cost) and the service's
    (``rate``, at most ``burst x rate / tenant_rate`` at once, never less than ``burst``).
    One tenant's frames therefore use at most ``tenant_rate`` per second over time and
    ``burst`` at once; with ``tenant_rate`` at most ``rate`` over the number of tenants, none
    can be starved by the others. A tenant's bucket is forgotten once full again (then it is
    a new one's equal), when more than ``max_tenants`` are held."""

    def __init__(
        self, rate: float, tenant_rate: float | None, burst: float, clock=time.monotonic,
        max_tenants: int = 4096,
    ) -> None:  # fmt: skip
        """``tenant_rate`` None or 0: no tenant has a part of its own (the service's bucket
        alone)."""
        self.tenant_rate = tenant_rate or None
        self.service = WorkBudget(rate, burst * max(1.0, rate / (self.tenant_rate or rate)), clock)
        self.burst, self.max_tenants, self._clock = burst, max_tenants, clock
        self._tenants: dict[str, WorkBudget] = {}
        self._lock = threading.Lock()  # held over each whole reservation and settlement

    @property
    def held(self) -> int:
        """Tenants' buckets held now (at most ``max_tenants`` plus those still refilling)."""
        with self._lock:
            return len(self._tenants)

    def _own(self, tenant: str, create: bool = True) -> WorkBudget | None:
        """``tenant``'s bucket (under the lock); None without tenant parts, or not held and
        not ``create``."""
        if self.tenant_rate is None:
            return None
        own = self._tenants.get(tenant)
        if own is None and create:
            if len(self._tenants) >= self.max_tenants:
                self._tenants = {t: b for t, b in self._tenants.items() if b.available() < b.burst}
            own = self._tenants[tenant] = WorkBudget(self.tenant_rate, self.burst, self._clock)
        return own

    def take(self, tenant: str, estimate_s: float) -> str | None:
        """Reserve ``estimate_s`` for ``tenant``: None when reserved, else why not, naming
        the option that refused it (nothing reserved)."""
        if estimate_s > self.burst:
            return f"one catch-up may cost at most {self.burst:g} s (--catch-up-burst)"
        with self._lock:
            own = self._own(tenant)
            if own is not None and own.take(estimate_s) is None:
                return (f"tenant {tenant!r} may use {own.available():.3g} s now ({own.rate:g} s per "
                        f"second, --tenant-catch-up-share)")  # fmt: skip
            if self.service.take(estimate_s) is None:
                if own is not None:
                    own.settle(estimate_s, 0.0)
                return (f"the service allows {self.service.available():.3g} s now ({self.service.rate:g} s "
                        f"per second, --catch-up-share)")  # fmt: skip
            return None

    def available(self, tenant: str) -> float:
        """What ``tenant`` may reserve now: the smaller of its own and the service's budget."""
        with self._lock:
            own = self._own(tenant, create=False)
            mine = own.available() if own is not None else self.burst
            return min(mine, self.service.available())

    def settle(self, tenant: str, estimate_s: float, actual_s: float) -> None:
        """The work ``tenant`` reserved at ``estimate_s`` cost ``actual_s``."""
        with self._lock:
            own = self._own(tenant)
            if own is not None:
                own.settle(estimate_s, actual_s)
            self.service.settle(estimate_s, actual_s)


def add_limit_options(p: argparse.ArgumentParser) -> None:
    """Every row of :data:`OPTIONS` as a parser option with the :class:`Limits` default."""
    default = Limits()
    for flag, name, kind, text in OPTIONS:
        p.add_argument(flag, dest=name, type=kind, default=getattr(default, name), help=text)


def limits_from(args: argparse.Namespace) -> Limits:
    """The :class:`Limits` of parsed :func:`add_limit_options` arguments."""
    return Limits(**{name: getattr(args, name) for _, name, _, _ in OPTIONS})


def gated(info: StepInfo, gate_p: float) -> bool:
    """Whether an update's innovation is too improbable to apply (a non-finite NIS is)."""
    if gate_p <= 0 or info.dof <= 0:
        return False
    return not math.isfinite(info.nis) or info.nis > _threshold(gate_p, info.dof)


def gated_step(
    filt: Any, belief: Any, u: np.ndarray, z: np.ndarray, valid: np.ndarray, rng: np.random.Generator,
    gate_p: float,
) -> tuple[Any, StepInfo]:  # fmt: skip
    """One lock-step step as a service session runs it: the step policy
    (:func:`~estimator_service.filters.policy.step_one`) with the service's innovation gate
    at ``gate_p``. In-process users who want the service's beliefs call this."""
    return step_one(filt, belief, u, z, valid, rng, gate_for(gate_p))


def gate_for(gate_p: float) -> Gate:
    """The innovation gate of a service at ``gate_p`` (:func:`gated`) for the step policy."""
    return functools.partial(gated, gate_p=gate_p)


@functools.lru_cache(maxsize=1024)
def _threshold(gate_p: float, dof: int) -> float:
    """The NIS whose chi-square tail probability with ``dof`` degrees of freedom is ``gate_p``."""
    return float(chi2.isf(gate_p, dof))


class ControlLog:
    """Streamed controls by time, at most ``cap`` of them (the latest); O(log n) per call."""

    def __init__(self, cap: int, control_dim: int) -> None:
        self._cap, self._zero = cap, np.zeros(control_dim)
        self._t: list[float] = []
        self._u: list[NDArray[np.float64]] = []

    def __len__(self) -> int:
        return len(self._t)

    def add(self, t: float, u: NDArray[np.float64]) -> None:
        i = bisect.bisect_right(self._t, t)
        self._t.insert(i, t)
        self._u.insert(i, u)
        if len(self._t) > self._cap:
            del self._t[0], self._u[0]

    def at(self, t: float) -> NDArray[np.float64]:
        """The latest control at or before ``t`` (zeros before the first)."""
        i = bisect.bisect_right(self._t, t + 1e-9)
        return self._u[i - 1] if i else self._zero

    def forget_before(self, t: float) -> None:
        """Drop controls superseded at ``t`` (the one in force at ``t`` stays)."""
        i = bisect.bisect_right(self._t, t + 1e-9) - 1
        if i > 0:
            del self._t[:i], self._u[:i]

    def clear(self) -> None:
        self._t.clear()
        self._u.clear()
