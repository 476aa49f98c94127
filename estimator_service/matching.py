"""Noise scales judged on held-out blocks of training flights.

A *block* is rows of a flight with models that never saw them (:mod:`estimator_service.crossfit`
fits one set of models per block). Training's calibration,
:func:`calibrate_by_likelihood`, chooses the scales that maximise the log-likelihood of the
truth under the EKF's beliefs over the blocks, every candidate of a block tracked in one
batched run (:func:`held_out_settings`), in two passes: factors on the one-step scales, then
each output's scale moved once by its ``e_i^2 / P_ii``.

The in-sample calibration of :func:`estimator_service.calibrate.calibrate_noise` keeps the
older rule: :func:`match_scales` chooses one process-noise scale per state output so that
the EKF's mean normalised squared error ``e_i^2 / P_ii`` is 1, in up to
:data:`MATCH_ROUNDS` sequential runs; :func:`coverage_curve` and :func:`covering_factor`
then choose the factor on both the process and the observation noise at which the truth
lies within 3 sigma on every dimension as often as it would for a Gaussian belief
(``0.9973 ** n``). Matched on the blocks pooled, the cameras-pinned position's process noise
went to 260-700 times its one-step value and cost 12 % RMS (200-point GP models, 8-minute
lab flight, four blocks); cross-fitting matched each block alone until the two passes
replaced the matching there.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from estimator_service.flight import Flight
from estimator_service.models.base import ObservationModel, PredictionModel
from estimator_service.tracking import TrackResult

__all__ = [
    "COVERAGE_FACTORS",
    "GAUSSIAN_WITHIN3",
    "LIKELIHOOD_FACTORS",
    "MATCH_ROUNDS",
    "MATCH_STEP",
    "MATCH_TOLERANCE",
    "MIN_LEVERAGE",
    "PROCESS_FACTORS",
    "REFINE_FACTORS",
    "RMS_TOLERANCE",
    "Block",
    "HeldOut",
    "LikelihoodChoice",
    "Setting",
    "adaptation_helps",
    "calibrate_by_likelihood",
    "choose_by_likelihood",
    "coverage",
    "coverage_curve",
    "covering_factor",
    "held_out",
    "held_out_settings",
    "leverage",
    "match_scales",
    "mean_e2_over_var",
    "nis_level",
    "track_block",
    "track_settings",
]

FloatArray = NDArray[np.float64]
GAUSSIAN_WITHIN3 = 0.9973  # P(|z| <= 3) for one Gaussian dimension
MATCH_ROUNDS = 8  # matching rounds
MATCH_STEP = 4.0  # the most one round changes an output's scale (either way)
MATCH_TOLERANCE = 0.1  # matching stops once every output's e^2 / P is within 10 % of 1
MIN_LEVERAGE = 0.25  # the weakest response of e^2 / P to its own scale that is followed
#: factors on the matched process and observation noise tried, smallest first
COVERAGE_FACTORS = (1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 4.0)
#: factors on the matched noise among which the held-out log-likelihood chooses
LIKELIHOOD_FACTORS = (0.5, 0.7, 1.0, 1.4, 2.0, 2.8, 4.0)
#: factors on the models' own process noise alone (errors that persist over many steps)
PROCESS_FACTORS = (2.0, 4.0, 8.0, 16.0, 32.0, 64.0)
#: factors on the second pass's matched scales (:func:`calibrate_by_likelihood`)
REFINE_FACTORS = (0.5, 0.7, 1.0, 1.4, 2.0)
#: a calibration raising the held-out RMS by more than this fraction is not applied
RMS_TOLERANCE = 0.02


@dataclass(frozen=True)
class Block:
    """Rows ``rows`` of ``flight`` and models (calibrated observation noise, raw prediction
    noise) that never saw them, with the models' process-variance ceiling ``(n,)`` and the
    system's process and observation noise floors (variances ``(n,)``, ``(m,)``; None:
    none), which apply to every scale tried on the block as they will in the filter."""

    flight: Flight
    rows: slice
    prediction: PredictionModel
    observation: ObservationModel
    ceiling: FloatArray | None = None
    process_floor: FloatArray | None = None
    obs_floor: FloatArray | None = None


@dataclass(frozen=True)
class Setting:
    """Noise scales tried on a block: on its raw models' process variance ``process (n,)``
    and observation variance ``observation (m,)``; the block's ceiling and floors apply
    after them, as they will in the filter."""

    process: FloatArray
    observation: FloatArray

    @classmethod
    def of(
        cls, block: Block, process: float | FloatArray = 1.0, observation: float | FloatArray = 1.0
    ) -> Setting:
        n, m = block.prediction.state_dim, block.observation.obs_dim
        return cls(
            np.broadcast_to(process, (n,)).astype(float), np.broadcast_to(observation, (m,)).astype(float)
        )


def track_settings(
    block: Block, settings: Sequence[Setting], adapt_reference: float | None = None
) -> list[TrackResult | None]:
    """The plain EKF over the block under each of ``settings`` (the adaptive one would hide
    what is calibrated here; with ``adapt_reference`` the adaptive one referred to that
    NIS/dof level), all tracked side by side in one batched run
    (:func:`~estimator_service.tracking.track_many`); None for a setting whose covariance
    blew up (not finite, or at some step no longer factorable, which the filter flags as
    divergence and carries on), which the callers count as a block the scales do not
    cover. Equal to tracking each setting alone up to the rounding of a batched call."""
    from estimator_service.models.calibration import RowMismatch

    try:
        return _track(block, settings, adapt_reference)
    except RowMismatch:  # a setting's prediction was not finite: the batch lost its row order
        return [_track(block, [s], adapt_reference)[0] for s in settings]


def _track(
    block: Block, settings: Sequence[Setting], adapt_reference: float | None
) -> list[TrackResult | None]:
    from estimator_service.factory import make_filter
    from estimator_service.models.calibration import NoiseScaledObservation, NoiseScaledPrediction
    from estimator_service.tracking import track_many

    rows = len(settings) > 1  # one scale per query row; a single setting scales every query
    proc = np.stack([s.process for s in settings]) if rows else settings[0].process
    seen = np.stack([s.observation for s in settings]) if rows else settings[0].observation
    obs = NoiseScaledObservation(block.observation, seen, block.obs_floor)
    pred = NoiseScaledPrediction(block.prediction, proc, block.ceiling, block.process_floor)
    adapt = {"adapt_rate": 0.0} if adapt_reference is None else {"adapt_reference": adapt_reference}
    filt = make_filter("ekf", pred, obs, system=block.flight.system, **adapt)
    try:
        with np.errstate(all="ignore"):
            runs = track_many(filt, block.flight, len(settings), rows=block.rows)
    except np.linalg.LinAlgError:  # other errors are bugs, not a covariance blown up
        return [None] * len(settings)
    return [r if _sound(r) else None for r in runs]


def _sound(r: TrackResult) -> bool:
    """Every belief of the run finite and factorable."""
    if not (np.isfinite(r.cov).all() and np.isfinite(r.mean).all()):
        return False
    try:
        np.linalg.cholesky(r.cov)
    except np.linalg.LinAlgError:
        return False
    return True


def track_block(
    block: Block, scale: FloatArray, factor: float = 1.0, obs_factor: float | None = None,
    adapt_reference: float | None = None,
) -> TrackResult | None:  # fmt: skip
    """:func:`track_settings` of one setting: the process noise scaled by ``scale * factor
    (n,)`` and the observation noise by ``obs_factor`` (default ``factor``)."""
    setting = Setting.of(block, scale * factor, factor if obs_factor is None else obs_factor)
    return track_settings(block, [setting], adapt_reference)[0]


def match_scales(
    blocks: Sequence[Block], scale: FloatArray, *, rounds: int = MATCH_ROUNDS, max_step: float = MATCH_STEP
) -> tuple[FloatArray, list[dict]]:
    """Process-noise scales ``(n,)`` from ``scale``: each round tracks every block and
    multiplies each output's scale by its ``e_i^2 / P_ii`` over all their steps raised to the inverse of
    its :func:`leverage` (the factor clipped to ``[1 / max_step, max_step]``); returns the
    scales and each round's NEES and ratios.

    One-step residuals alone miss errors that persist over many steps (gusts with a 3 s
    correlation time, actuator lag, an unobserved drift such as the yaw's): on a held-out
    flight the yaw's ``e^2 / P`` was 14 with one-step scales.
    """
    history, last = [], None  # last: the previous round's (scale, z2), for the leverage
    for _ in range(rounds):
        if history and history[-1]["e2_over_var"] is not None and _converged(history[-1]["e2_over_var"]):
            break
        runs = [r for r in (track_block(b, scale) for b in blocks) if r is not None]
        if not runs:  # every block blew up: keep the last scales that tracked
            history.append({"nees": None, "e2_over_var": None})
            return (last[0] if last is not None else scale), history
        z2 = mean_e2_over_var(runs)
        z2 = np.nan_to_num(z2, nan=max_step, posinf=max_step)
        nees = float(np.mean([r.scores()["nees"] for r in runs]))
        history.append({"nees": nees, "e2_over_var": z2.tolist()})
        power = 1.0 if last is None else 1.0 / leverage(last, (scale, z2))
        last = (scale, z2)
        scale = scale * np.clip(z2**power, 1 / max_step, max_step)
    return scale, history


def mean_e2_over_var(runs: Sequence[TrackResult]) -> FloatArray:
    """Per state output, ``e_i^2 / P_ii`` averaged over every step of ``runs`` ``(n,)`` (1 for
    a consistent belief; NaN or inf where a variance is 0, which each caller maps)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.concatenate([r.error**2 / np.diagonal(r.cov, axis1=1, axis2=2) for r in runs]).mean(axis=0)


def _converged(z2: list[float]) -> bool:
    return bool(np.all(np.abs(np.log(np.maximum(z2, 1e-12))) <= math.log(1 + MATCH_TOLERANCE)))


def leverage(before: tuple[FloatArray, FloatArray], after: tuple[FloatArray, FloatArray]) -> FloatArray:
    """Per output, how strongly ``e^2 / P`` fell as its process-noise scale rose between two
    rounds, ``-d log(e^2/P) / d log(scale)`` in ``[MIN_LEVERAGE, 1]`` (1 where the scale did
    not move or the ratio rose). A state the sensors pin (the yaw, the position) has a
    posterior variance near ``sqrt(Q R)``, so its ratio falls about as ``scale^-1/2``."""
    ds = np.log(after[0] / before[0])
    dz = np.log(np.maximum(after[1], 1e-12) / np.maximum(before[1], 1e-12))
    with np.errstate(divide="ignore", invalid="ignore"):
        lev = np.where(np.abs(ds) > 1e-3, -dz / ds, 1.0)
    return np.clip(np.nan_to_num(lev, nan=1.0), MIN_LEVERAGE, 1.0)


def coverage_curve(blocks: Sequence[Block], scale: FloatArray) -> list[float]:
    """Per factor of :data:`COVERAGE_FACTORS` up to the first that reaches a Gaussian
    belief's ``0.9973 ** n`` (the larger ones are not tracked), the fraction of all the
    blocks' steps on which the EKF keeps the truth within 3 sigma on every dimension."""
    return coverage(blocks, scale)[0]


def coverage(blocks: Sequence[Block], scale: FloatArray) -> tuple[list[float], float]:
    """:func:`coverage_curve`, and the :func:`nis_level` of the EKF's runs at the last
    factor tracked (the one :func:`covering_factor` chooses from that curve)."""
    from estimator_service.tracking import within_3sigma

    curve: list[float] = []
    level = math.nan
    for factor in COVERAGE_FACTORS:
        if curve and curve[-1] >= GAUSSIAN_WITHIN3 ** len(scale):
            break
        runs = [track_block(b, scale, factor) for b in blocks]
        inside = sum(within_3sigma(r.error, r.cov) * len(r.error) for r in runs if r is not None)
        steps = sum(len(r.error) if r is not None else len(range(len(b.flight))[b.rows]) - 1
                    for r, b in zip(runs, blocks, strict=True))  # fmt: skip
        curve.append(float(inside / max(1, steps)))
        level = nis_level([r for r in runs if r is not None])
    return curve, level


def nis_level(runs: Sequence[TrackResult]) -> float:
    """The mean NIS/dof over every update of ``runs`` (NaN without one): the innovation
    level the adaptive filters refer their process-noise factor to
    (:mod:`estimator_service.filters.adaptive`); 1 for a consistent filter."""
    ratios = [r.nis[r.dof > 0] / r.dof[r.dof > 0] for r in runs]
    flat = np.concatenate(ratios) if ratios else np.zeros(0)
    flat = flat[np.isfinite(flat)]
    return float(np.mean(flat)) if flat.size else math.nan


def covering_factor(curve: Sequence[float], state_dim: int) -> float:
    """The smallest of :data:`COVERAGE_FACTORS` whose :func:`coverage_curve` value reaches a
    Gaussian belief's ``0.9973 ** n`` (the largest factor when none does).

    Matched second moments still leave the bursts of persistent errors outside the bounds
    more often than a Gaussian belief would. Scaling the process and the observation noise
    together scales a linear filter's whole covariance, so the states the sensors pin (whose
    spread hardly follows their process noise) widen too."""
    hits = np.flatnonzero(np.asarray(curve) >= GAUSSIAN_WITHIN3**state_dim)
    return COVERAGE_FACTORS[int(hits[0]) if hits.size else -1]


@dataclass(frozen=True)
class HeldOut:
    """The plain EKF's scores pooled over held-out blocks: mean log-likelihood of the truth
    per step (``-inf`` when a block's covariance blew up), aggregate RMS (the mean of the
    system's group RMS values), mean NIS/dof, per state the fraction of steps within 1,
    2 and 3 standard deviations ``coverage[k - 1] (n,)`` and the mean ``e_i^2 / P_ii``
    ``e2_over_var (n,)`` (1 for a consistent belief)."""

    mll: float
    rms: float
    nis_level: float
    coverage: tuple[tuple[float, ...], ...] = ()
    e2_over_var: tuple[float, ...] = ()

    def as_dict(self) -> dict:
        return {"mll": self.mll, "rms": self.rms, "nis_level": self.nis_level,
                "coverage": [list(c) for c in self.coverage],
                "e2_over_var": list(self.e2_over_var)}  # fmt: skip


def held_out(
    blocks: Sequence[Block], scale: FloatArray, factor: float = 1.0, obs_factor: float | None = None,
    adapt_reference: float | None = None,
) -> HeldOut:  # fmt: skip
    """:class:`HeldOut` of :func:`track_block` over ``blocks`` at ``scale * factor`` (and
    the observation noise times ``obs_factor``, default ``factor``; the adaptive EKF with
    ``adapt_reference``)."""
    obs = factor if obs_factor is None else obs_factor
    settings = [[Setting.of(b, scale * factor, obs)] for b in blocks]
    return held_out_settings(blocks, settings, adapt_reference)[0]


def held_out_settings(
    blocks: Sequence[Block], settings: Sequence[Sequence[Setting]], adapt_reference: float | None = None
) -> list[HeldOut]:
    """:class:`HeldOut` of each setting, ``settings[i][j]`` on block ``i`` (setting ``j`` may
    differ by block: each block's own matched scales), the settings of a block tracked side by
    side (:func:`track_settings`)."""
    runs = [track_settings(b, s, adapt_reference) for b, s in zip(blocks, settings, strict=True)]
    return [_pooled([r[j] for r in runs], blocks) for j in range(len(settings[0]))]


def _pooled(runs: Sequence[TrackResult | None], blocks: Sequence[Block]) -> HeldOut:
    from estimator_service.tracking import aggregate_rms, coverage_by_sigma, group_rms

    if any(r is None for r in runs) or not runs:
        return HeldOut(-math.inf, math.inf, math.nan)
    steps = np.array([len(r.error) for r in runs])
    mll = float(np.sum([r.scores()["mll"] * k for r, k in zip(runs, steps, strict=True)]) / steps.sum())
    err = np.concatenate([r.error for r in runs])
    groups = blocks[0].flight.system.groups
    cover = tuple(
        tuple(c.round(4).tolist())
        for c in coverage_by_sigma(err, np.concatenate([r.cov for r in runs])).values()
    )
    z2 = tuple(
        np.nan_to_num(mean_e2_over_var(runs), nan=1.0, posinf=MATCH_STEP).tolist()
    )  # 0 / 0: exact, certain
    return HeldOut(mll, aggregate_rms(group_rms(err, groups), groups), nis_level(runs), cover, z2)


@dataclass(frozen=True)
class LikelihoodChoice:
    """The calibration with the highest held-out log-likelihood among those that score
    above the uncalibrated models and raise the RMS by at most :data:`RMS_TOLERANCE`: a
    factor on a shape of process and observation scales (``family``: "matched", or in
    :func:`calibrate_by_likelihood` "one-step" and "matched") or on the models' own process
    noise alone ("process"), with the chosen scales ``process (n,)`` and ``observation
    (m,)``; ``applied`` False when none qualifies (``reason`` says why; the scales are then
    those of the best candidate, not applied). ``origin``: for the second pass's "matched"
    family, the first-pass candidate its scales were moved from (e.g. "one-step x1.4")."""

    applied: bool
    family: str
    factor: float
    chosen: HeldOut
    uncalibrated: HeldOut
    curve: dict[str, float]
    reason: str
    process: FloatArray
    observation: FloatArray
    origin: str = ""

    def details(self) -> dict:
        return {"applied": self.applied, "family": self.family, "factor": self.factor, "reason": self.reason,
                "from": self.origin, "chosen": self.chosen.as_dict(),
                "uncalibrated": self.uncalibrated.as_dict(), "mll_by_factor": self.curve}  # fmt: skip


Candidate = tuple[str, float]  # (family, factor)
Shape = tuple[FloatArray, FloatArray]  # process (n,) and observation (m,) scales
RAW: Candidate = ("raw", 1.0)  # the uncalibrated models


def choose_by_likelihood(
    blocks: Sequence[Block], scale: FloatArray, obs_scale: FloatArray, family: str = "matched"
) -> LikelihoodChoice:
    """Among :data:`LIKELIHOOD_FACTORS` on the process scales ``scale (n,)`` and
    observation scales ``obs_scale (m,)`` together (``family``), and :data:`PROCESS_FACTORS`
    on the ``blocks``' own (raw) process noise alone, the calibration with the highest
    held-out log-likelihood of the truth that beats the raw (uncalibrated) models' and raises
    their RMS by at most :data:`RMS_TOLERANCE`. Every candidate of a block is tracked in one
    batched run."""
    return _first_pass(blocks, scale, obs_scale, family)[-1]


def _first_pass(
    blocks: Sequence[Block], scale: FloatArray, obs_scale: FloatArray, family: str
) -> tuple[dict[Candidate, Shape], dict[Candidate, HeldOut], HeldOut, LikelihoodChoice]:
    """:func:`choose_by_likelihood`'s candidates, their scores (the raw models' apart) and
    its choice."""
    candidates = _candidates(scale, obs_scale, family)
    scored = _score(blocks, candidates)
    base = scored.pop(RAW)
    return candidates, scored, base, _choose(scored, candidates, base)


def calibrate_by_likelihood(
    blocks: Sequence[Block], start: FloatArray, obs_scale: FloatArray,
    on_pass: Callable[[str], None] | None = None,
) -> LikelihoodChoice:  # fmt: skip
    """Noise scales chosen by the held-out log-likelihood in two batched passes over the
    blocks. First the candidates of :func:`choose_by_likelihood` on the one-step process
    scales ``start (n,)`` and the frames' observation scales ``obs_scale (m,)`` (family
    "one-step"); then, from the best of them, each output's process scale moved once by its
    pooled ``e_i^2 / P_ii`` (by at most :data:`MATCH_STEP` either way; observation scales
    kept), times :data:`REFINE_FACTORS` (family "matched"). The best of both passes that
    beats the raw models without raising their RMS by more than :data:`RMS_TOLERANCE`.
    ``on_pass(label)`` after each pass.

    It replaced up to :data:`MATCH_ROUNDS` sequential EKF runs per block that matched every
    output's ``e^2 / P`` to 1 before the choice; one batched pass costs about two single
    runs (docs/measurements.md#calibration-cost). Moving each output by ``e^2 / P`` raised to
    the inverse of its leverage (about the square for a state the sensors pin) scored lower
    on every kind's held-out blocks (200-point models: 26.92 vs 27.17 for gp, 26.93 vs 27.40
    for sparse) and was dropped."""
    candidates, scored, base, first = _first_pass(blocks, start, obs_scale, "one-step")
    if on_pass is not None:
        on_pass("first pass")
    if not math.isfinite(first.chosen.mll):
        if on_pass is not None:  # every candidate blew up: nothing to move from
            on_pass("second pass (none)")
        return first
    moved = first.process * np.clip(np.asarray(first.chosen.e2_over_var), 1 / MATCH_STEP, MATCH_STEP)
    refined: dict[Candidate, Shape] = {
        ("matched", f): (moved * f, first.observation * f) for f in REFINE_FACTORS
    }
    scored |= _score(blocks, refined)
    if on_pass is not None:
        on_pass("second pass")
    choice = _choose(scored, candidates | refined, base)
    origin = f"{first.family} x{first.factor:g}" if choice.family == "matched" else ""
    return dataclasses.replace(choice, origin=origin)


def _candidates(scale: FloatArray, obs_scale: FloatArray, family: str) -> dict[Candidate, Shape]:
    """The raw models, ``family`` x :data:`LIKELIHOOD_FACTORS` on ``scale (n,)`` and
    ``obs_scale (m,)``, and "process" x :data:`PROCESS_FACTORS` on the raw process noise."""
    n, m = len(scale), len(obs_scale)
    candidates: dict[Candidate, Shape] = {RAW: (np.ones(n), np.ones(m))}
    candidates |= {(family, f): (scale * f, obs_scale * f) for f in LIKELIHOOD_FACTORS}
    candidates |= {("process", f): (np.full(n, f), np.ones(m)) for f in PROCESS_FACTORS}
    return candidates


def _score(blocks: Sequence[Block], candidates: dict[Candidate, Shape]) -> dict[Candidate, HeldOut]:
    """:class:`HeldOut` of every candidate, all of a block's tracked side by side."""
    settings = [[Setting.of(b, p, o) for p, o in candidates.values()] for b in blocks]
    return dict(zip(candidates, held_out_settings(blocks, settings), strict=True))


def _choose(
    scored: dict[Candidate, HeldOut], candidates: dict[Candidate, Shape], base: HeldOut
) -> LikelihoodChoice:
    """The :class:`LikelihoodChoice` among ``scored`` against the raw models' ``base``."""
    fair = [k for k, v in scored.items() if v.mll > base.mll and v.rms <= base.rms * (1 + RMS_TOLERANCE)]
    best = max(fair or scored, key=lambda k: scored[k].mll)
    top = scored[best]
    if fair:
        reason = "applied"
    elif not top.mll > base.mll:
        reason = f"held-out log-likelihood {top.mll:.4g} not above the uncalibrated {base.mll:.4g}"
    else:
        reason = (f"every calibration scoring a higher held-out log-likelihood raised the RMS more than "
                  f"{RMS_TOLERANCE:.0%} (best: {top.rms:.4g} against {base.rms:.4g})")  # fmt: skip
    curve = {f"{family} x{f:g}": v.mll for (family, f), v in scored.items()}
    return LikelihoodChoice(bool(fair), best[0], best[1], top, base, curve, reason, *candidates[best])


def adaptation_helps(blocks: Sequence[Block], setting: Setting, plain: HeldOut) -> tuple[bool, HeldOut]:
    """Whether the adaptive EKF, referred to ``plain``'s NIS/dof level, scores a higher
    held-out log-likelihood than the ``plain`` EKF at the same noise ``setting`` without
    raising its RMS by more than :data:`RMS_TOLERANCE`; and its scores."""
    level = plain.nis_level if math.isfinite(plain.nis_level) and plain.nis_level > 0 else 1.0
    adaptive = held_out_settings(blocks, [[setting] for _ in blocks], adapt_reference=level)[0]
    return adaptive.mll > plain.mll and adaptive.rms <= plain.rms * (1 + RMS_TOLERANCE), adaptive
