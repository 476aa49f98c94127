"""Run a filter over a recorded flight and score it against the ground truth.

Scores are per state group of the flight's :class:`~estimator_service.system.System` (the
blimp's: mm, deg, mm/s, deg/s as in the paper's tables), plus the consistency figures:
average NEES and NIS/dof (with the bands a consistent filter stays in), the fraction of
steps with the truth outside the 3-sigma ellipsoid, and the paper's failure flag.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2, norm

from estimator_service.filters import GaussianBelief, StepInfo, make_pd
from estimator_service.filters.policy import step_many, update_many
from estimator_service.flight import Flight
from estimator_service.system import Group, System

__all__ = [
    "FAILED_SHARE",
    "GAUSSIAN_COVERAGE",
    "GROUPS",
    "LOST_ANGLE_SHARE",
    "RELIABILITY_LEVELS",
    "TrackResult",
    "aggregate_rms",
    "coverage_by_sigma",
    "group_mean_norm",
    "group_rms",
    "lost_angle_sd",
    "lost_angle_steps",
    "mean_sd",
    "reliability",
    "score",
    "segment_rows",
    "segments",
    "state_error",
    "track_flight",
    "within_3sigma",
]

FloatArray = NDArray[np.float64]


@functools.lru_cache(maxsize=1)
def _blimp() -> System:
    from estimator_service.blimp import blimp_system

    return blimp_system()


def _blimp_groups() -> tuple[Group, ...]:
    return _blimp().groups


#: the blimp's groups as ``{name: (slice, unit factor)}`` (paper units: mm, deg, mm/s, deg/s)
GROUPS = {g.name: (slice(g.indices[0], g.indices[-1] + 1), g.factor) for g in _blimp_groups()}


def state_error(estimate: FloatArray, truth: FloatArray, system: System | None = None) -> FloatArray:
    """``estimate - truth`` for states ``(T, n)`` with the angle errors wrapped (the blimp's
    Euler angles when ``system`` is None)."""
    return (system or _blimp()).state_error(estimate, truth)


def group_rms(err: FloatArray, groups: Sequence[Group] | None = None) -> dict[str, float]:
    """RMS of state errors ``(T, n)`` per group, in the group's units (the blimp's
    :data:`GROUPS` when ``groups`` is None)."""
    gs = _blimp_groups() if groups is None else groups
    return {g.name: float(np.sqrt(np.mean(err[:, _columns(g.indices)] ** 2)) * g.factor) for g in gs}


def group_mean_norm(err: FloatArray, groups: Sequence[Group] | None = None) -> dict[str, float]:
    """Mean over steps of the error norm ``(T, n)`` per group, in the group's units (the
    measure of the paper's Tables 5 and 6, beside :func:`group_rms`)."""
    gs = _blimp_groups() if groups is None else groups
    return {
        g.name: float(np.mean(np.linalg.norm(err[:, _columns(g.indices)], axis=1)) * g.factor) for g in gs
    }


def _columns(indices: tuple[int, ...]) -> slice | list[int]:
    """A slice for consecutive indices (a view: the same summation order as before groups
    were configurable, so scores are bit-identical), else the index list."""
    if list(indices) == list(range(indices[0], indices[0] + len(indices))):
        return slice(indices[0], indices[0] + len(indices))
    return list(indices)


@dataclass(frozen=True)
class TrackResult:
    """Per-step estimates and scores of one tracking run.

    Attributes
    ----------
    mean, cov: (T, 12), (T, 12, 12)
        Beliefs after each step (row ``k`` estimates the flight's row ``k + 1``).
    truth: (T, 12)
    nis, dof: (T,)
        Normalised innovation squared and its degrees of freedom (0: no camera).
    diverged: (T,) bool
    step_s
        Mean wall time per filter step (s).
    exact: (T, 12) or None
        The simulator's exact states, when the flight has them (``truth`` is then the
        measured ground truth).
    """

    mean: FloatArray
    cov: FloatArray
    truth: FloatArray
    nis: FloatArray
    dof: NDArray[np.int64]
    diverged: NDArray[np.bool_]
    step_s: float
    system: System | None = None
    exact: FloatArray | None = None

    @property
    def error(self) -> FloatArray:
        return state_error(self.mean, self.truth, self.system)

    def __repr__(self) -> str:
        return f"TrackResult(steps={len(self.mean)}, step_ms={self.step_s * 1e3:.3g})"

    def scores(self) -> dict[str, float]:
        return score(self)


def track_flight(
    filt,
    flight: Flight,
    *,
    rng: np.random.Generator | None = None,
    init_std: FloatArray | None = None,
    rows: slice = slice(None),
    on_step: Callable[[int], None] | None = None,
) -> TrackResult:
    """Filter ``flight`` (within its first episode segment ``rows``) starting at the truth.

    The initial belief is the true first state with standard deviations ``init_std``
    (default: the blimp's 5 cm, 2 deg, 5 cm/s, 2 deg/s; a tenth of each component's spread
    in the flight for other systems). Each step predicts with the recorded control and
    updates with the sensors that delivered a reading at the next row, under the step
    policy of :func:`~estimator_service.filters.policy.step_many`. ``filt`` is any filter
    of the common interface (``initial``, ``step``, ``gaussian``).
    """
    return track_many(filt, flight, 1, rng=rng, init_std=init_std, rows=rows, on_step=on_step)[0]


def track_many(
    filt,
    flight: Flight,
    count: int,
    *,
    rng: np.random.Generator | None = None,
    init_std: FloatArray | None = None,
    rows: slice = slice(None),
    on_step: Callable[[int], None] | None = None,
) -> list[TrackResult]:
    """:func:`track_flight` of ``count`` beliefs side by side, all fed the flight's controls
    and readings, in one batched filter step per row (one model call for all of them where
    the filter batches). With models whose noise differs per query row
    (:class:`~estimator_service.models.calibration.NoiseScaledPrediction` with ``(count, n)``
    scales) it tracks ``count`` noise settings at the cost of little more than one; ``step_s``
    is the wall time of a batched step."""
    fl = flight.select(np.arange(len(flight))[rows])
    ep = fl.episode == fl.episode[0]
    n = int(np.argmin(ep)) if not ep.all() else len(fl)
    std = init_std if init_std is not None else _default_init_std(fl)
    rng = rng or np.random.default_rng(0)
    beliefs = [filt.initial(GaussianBelief(fl.state[0].copy(), np.diag(std**2)), rng) for _ in range(count)]
    valid_all = fl.expand_valid()
    means, covs = np.empty((count, max(n - 1, 0), fl.state.shape[1])), None
    nis, dof = np.full((count, max(n - 1, 0)), np.nan), np.zeros((count, max(n - 1, 0)), np.int64)
    div = np.zeros((count, max(n - 1, 0)), bool)
    ones = np.ones((count, 1))
    t0 = time.perf_counter()
    for k in range(n - 1):
        u, z, valid = ones * fl.control[k], ones * fl.z[k + 1], ones.astype(bool) & valid_all[k + 1]
        out = step_many(filt, beliefs, u, z, valid, rng=rng)
        if fl.extra is not None:
            out = _extra_updates(filt, out, fl, k + 1, rng)
        beliefs = [b for b, _ in out]
        gs = [filt.gaussian(b) for b in beliefs]
        if covs is None:
            covs = np.empty((count, max(n - 1, 0), *gs[0].cov.shape))
        for i, (g, (_, info)) in enumerate(zip(gs, out, strict=True)):
            means[i, k], covs[i, k] = g.mean, g.cov
            nis[i, k], dof[i, k], div[i, k] = info.nis, info.dof, info.diverged
        if on_step:
            on_step(k + 1)
    step_s = (time.perf_counter() - t0) / max(1, n - 1)
    if covs is None:
        covs = np.empty((count, 0, fl.state.shape[1], fl.state.shape[1]))
    exact = None if fl.exact is None else fl.exact[1:n]
    return [TrackResult(means[i], covs[i], fl.state[1:n], nis[i], dof[i], div[i], step_s, fl.system, exact)
            for i in range(count)]  # fmt: skip


def _extra_updates(filt, out: list, fl: Flight, row: int, rng: np.random.Generator) -> list:
    """Update every belief of ``out`` with the row's extra readings one after another (a
    sensor's second and later readings within the step,
    :class:`~estimator_service.flight.ExtraReadings`); a step's NIS and degrees of freedom
    add up over its updates."""
    extra = fl.extra
    for i in extra.at(row):
        v = fl.system.expand_valid(extra.valid[i])
        valid = np.broadcast_to(v, (len(out), v.size))
        more = update_many(
            filt, [b for b, _ in out], np.broadcast_to(extra.z[i], valid.shape), valid, rng=rng
        )
        out = [(b, _added(info, m)) for (b, m), (_, info) in zip(more, out, strict=True)]
    return out


def _added(info: StepInfo, more: StepInfo) -> StepInfo:
    """A step's report after one more update ``more``: NIS and degrees of freedom add up."""
    if not more.dof:
        return info
    nis = more.nis if not info.dof else info.nis + more.nis
    return StepInfo(nis, info.dof + more.dof, info.diverged or more.diverged)


def _default_init_std(flight: Flight) -> FloatArray:
    if flight.system.name == "blimp":
        return np.repeat([0.05, 0.035, 0.05, 0.035], 3)
    return np.maximum(0.1 * flight.state.std(axis=0), 1e-6)


def score(r: TrackResult) -> dict[str, float]:
    """RMS errors per state group (paper units), mean log-likelihood of the truth,
    average NEES and NIS/dof with the 95% bands a consistent filter's averages fall in
    (``nees_lo``/``nees_hi``, ``nis_lo``/``nis_hi``), NEES per state dimension
    (``nees_per_dim``, 1 if consistent), the worst and best dimension's coverage within 1, 2
    and 3 sigma (``coverage<k>_min``/``_max``; Gaussian 0.683, 0.954, 0.997), the fraction
    of steps outside the 3-sigma ellipsoid, the fractions with the truth within 3 sigma on every dimension
    (``within3``) and on every dimension of each group (``within3_<group>``), and a
    failure flag; with the simulator's exact states also the RMS errors against them
    (``exact_<group>``).

    A run fails when the truth is outside the 3-sigma ellipsoid of the estimate
    (chi-square 99.73% with ``n`` degrees of freedom) on more than 10% of the steps, or
    when the belief has lost an angle (:func:`lost_angle_steps`, ``lost_steps``) on more
    than 10% of them: a belief wide enough to hold any truth has lost track too.
    """
    e = r.error
    n = e.shape[1]
    groups = None if r.system is None else r.system.groups
    out = group_rms(e, groups)
    if r.exact is not None:
        exact = group_rms(state_error(r.mean, r.exact, r.system), groups)
        out.update({f"exact_{k}": v for k, v in exact.items()})
    try:
        ls = np.linalg.cholesky(r.cov)
    except np.linalg.LinAlgError:  # a collapsed particle cloud: factor each step robustly
        ls = np.stack([make_pd(c)[1] for c in r.cov])
    w = np.linalg.solve(ls, e[:, :, None])[:, :, 0]
    nees = np.sum(w * w, axis=1)
    logdet = 2 * np.sum(np.log(np.diagonal(ls, axis1=1, axis2=2)), axis=1)
    out["mll"] = float(np.mean(-0.5 * (nees + logdet + n * math.log(2 * math.pi))))
    out["nees"] = float(np.mean(nees))
    has = r.dof > 0
    out["nis_per_dof"] = float(np.mean(r.nis[has] / r.dof[has])) if has.any() else math.nan
    out["nees_var"], out["nis_var"] = consistent_variances(len(nees), r.dof, r.truth.shape[1])
    out["nees_lo"], out["nees_hi"] = consistency_band(float(n), out["nees_var"])  # 95% if consistent
    out["nis_lo"], out["nis_hi"] = consistency_band(1.0, out["nis_var"])
    outside = float(np.mean(nees > chi2.ppf(0.9973, n)))
    out["outside_3sigma"] = outside
    out["within3"] = within_3sigma(e, r.cov)
    out["nees_per_dim"] = out["nees"] / n
    for k, cover in coverage_by_sigma(e, r.cov).items():  # per dimension: the worst and the best
        out[f"coverage{k}_min"], out[f"coverage{k}_max"] = float(cover.min()), float(cover.max())
    for g in _blimp_groups() if r.system is None else r.system.groups:
        cols = list(g.indices)
        out[f"within3_{g.name}"] = within_3sigma(e[:, cols], r.cov[:, cols][:, :, cols])
    out["lost_steps"] = float(np.mean(lost_angle_steps(r.cov, (r.system or _blimp()).state_periods)))
    out["failed"] = float(outside > FAILED_SHARE or out["lost_steps"] > FAILED_SHARE)
    out["step_ms"] = r.step_s * 1e3
    out["diverged_steps"] = float(np.sum(r.diverged))
    return out


#: a run fails when more of its steps than this are outside 3 sigma, or lost (:func:`score`)
FAILED_SHARE = 0.10
#: an angle's belief is lost when its standard deviation exceeds this share of a belief that
#: knows nothing (uniform on the circle: period / sqrt(12); for a full turn 103.9 deg, so 52 deg)
LOST_ANGLE_SHARE = 0.5


def lost_angle_sd(period: float) -> float:
    """The standard deviation above which an angle of ``period`` counts as lost."""
    return LOST_ANGLE_SHARE * period / math.sqrt(12.0)


def lost_angle_steps(cov: FloatArray, periods: Sequence[float]) -> NDArray[np.bool_]:
    """``(T,)``: the steps at which the belief ``cov (T, n, n)`` has lost an angle (the
    components with a period in ``periods (n,)``; none: never lost)."""
    periods = np.asarray(periods, dtype=float)
    angles = np.flatnonzero(periods > 0)
    if angles.size == 0:
        return np.zeros(cov.shape[0], dtype=bool)
    var = np.diagonal(cov, axis1=1, axis2=2)[:, angles]
    limit = np.array([lost_angle_sd(p) for p in periods[angles]])
    return np.any(~(var <= limit**2), axis=1)  # NaN variances count as lost


#: per-dimension coverage of a Gaussian belief within 1, 2 and 3 standard deviations
GAUSSIAN_COVERAGE = {1: 0.6827, 2: 0.9545, 3: 0.9973}


def coverage_by_sigma(error: FloatArray, cov: FloatArray) -> dict[int, FloatArray]:
    """``{k: (n,)}`` for k = 1, 2, 3: per dimension, the fraction of steps whose error
    ``(T, n)`` lies within ``k`` standard deviations of the belief ``cov (T, n, n)``
    (a calibrated Gaussian belief: :data:`GAUSSIAN_COVERAGE`)."""
    inside = _within(error, cov, np.array(list(GAUSSIAN_COVERAGE), dtype=float))
    return {k: inside[i].mean(axis=0) for i, k in enumerate(GAUSSIAN_COVERAGE)}


def _within(error: FloatArray, cov: FloatArray, k: FloatArray) -> NDArray[np.bool_]:
    """``(K, T, n)``: whether each error ``(T, n)`` lies within ``k (K,)`` standard deviations
    of its belief ``cov (T, n, n)`` (a zero standard deviation covers only an exact 0)."""
    sd = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0))
    return np.abs(error)[None] <= k[:, None, None] * sd[None]


#: nominal central coverages of a reliability diagram (a Gaussian belief's interval mean +- z sd)
RELIABILITY_LEVELS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.683, 0.8, 0.9, 0.954, 0.99, 0.997)


def reliability(
    error: FloatArray, cov: FloatArray, groups: Sequence[Group] | None = None,
    levels: Sequence[float] = RELIABILITY_LEVELS,
) -> dict[str, FloatArray]:  # fmt: skip
    """A reliability diagram's points per state group.

    Parameters
    ----------
    error: (T, n)
        Estimate minus truth.
    cov: (T, n, n)
        The beliefs' covariances.
    groups
        State groups (default: the blimp's).
    levels: (L,)
        Nominal central coverages ``p``.

    Returns
    -------
    dict
        ``{group: (L,)}``: for each ``p``, the fraction of steps and of the group's dimensions
        whose error lies within the belief's ``norm.ppf((1 + p) / 2)`` standard deviations.
        A calibrated Gaussian belief lies on the diagonal; points below it are
        overconfident, above it too wide.
    """
    inside = _within(error, cov, norm.ppf((1.0 + np.asarray(levels, dtype=float)) / 2.0))  # (L, T, n)
    return {g.name: inside[:, :, list(g.indices)].mean(axis=(1, 2)) for g in groups or _blimp_groups()}


def within_3sigma(error: FloatArray, cov: FloatArray) -> float:
    """Fraction of steps whose error ``(T, n)`` lies within 3 standard deviations of the
    belief ``cov (T, n, n)`` on every dimension (Gaussian expectation ``0.9973 ** n``: 0.968
    for the blimp's 12)."""
    sd = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0))
    return float(np.mean(np.all(np.abs(error) <= 3.0 * sd, axis=1)))


def consistent_variances(steps: int, dof: NDArray[np.int64], state_dim: int = 12) -> tuple[float, float]:
    """Variances of the time-averaged NEES and NIS/dof of a consistent filter.

    NEES at each of ``steps`` steps is chi-square with ``state_dim`` degrees of freedom
    (variance ``2 state_dim``); NIS/dof at a step with ``d = dof[k] > 0`` has variance
    ``2 / d``; steps are treated as independent.
    """
    has = dof > 0
    nis = float(np.sum(2.0 / dof[has]) / has.sum() ** 2) if has.any() else math.nan
    return 2.0 * state_dim / max(steps, 1), nis


def consistency_band(mean: float, var_of_mean: float, level: float = 0.95) -> tuple[float, float]:
    """Central ``level`` band of an average with this mean and variance, as a scaled
    chi-square law ``mean * chi2(k) / k`` with ``k = 2 mean^2 / var`` degrees of freedom.

    Exact for the average NEES of a consistent filter (``k = state_dim * steps``); for NIS/dof
    with a varying number of cameras it matches the first two moments.
    """
    if not (math.isfinite(var_of_mean) and var_of_mean > 0 and mean > 0):
        return math.nan, math.nan
    k = 2.0 * mean * mean / var_of_mean
    tail = 0.5 * (1.0 - level)
    return float(mean * chi2.ppf(tail, k) / k), float(mean * chi2.ppf(1.0 - tail, k) / k)


def aggregate_rms(scores: dict[str, float], groups: Sequence[Group] | None = None) -> float:
    """One number per run: the mean of the group RMS values (the blimp's four groups in paper
    units when ``groups`` is None)."""
    return float(np.mean([scores[g.name] for g in (_blimp_groups() if groups is None else groups)]))


def segments(n_rows: int, seg: int, length: int | None = None) -> list[slice]:
    """Consecutive blocks of ``seg`` rows of an ``n_rows`` flight, each cut to its first
    ``length`` rows (all ``seg`` when None); the whole flight when it is shorter than one."""
    use = seg if length is None else length
    return [slice(a, a + use) for a in range(0, n_rows - seg + 1, seg)] or [slice(None)]


def segment_rows(n_rows: int, seg: int, length: int | None = None) -> int:
    """The rows :func:`segments` ``(n_rows, seg, length)`` cover together."""
    return sum(len(range(n_rows)[r]) for r in segments(n_rows, seg, length))


def mean_sd(runs: list[dict[str, float]]) -> dict[str, list[float]]:
    """``{key: [mean, sd]}`` over runs that share their keys."""
    return {k: [float(np.mean([r[k] for r in runs])), float(np.std([r[k] for r in runs]))] for k in runs[0]}
