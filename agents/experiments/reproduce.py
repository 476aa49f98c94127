"""``gpbf reproduce``: the paper's experiments (Sect. 6) on simulated flights.

Tables 5/6 (one-step prediction and observation errors), Tables 7-9 (tracking with
UKF/EKF/PF x Param/GP/EGP/hetGP/sparse: RMS improvement over the parametric filter,
per state group and averaged over the groups as Table 7 does, mean log-likelihood, time
per step), Fig. 4 (no training data with the tail pushing left),
Table 10 (the synthetic landmark robot) and filter consistency (NEES, NIS), with k-fold
cross-validation over contiguous blocks of one long scripted flight.
"""

from __future__ import annotations

import math
import time
from contextlib import nullcontext
from dataclasses import asdict, dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np

from agents.experiments.fig5 import fig5
from agents.experiments.landmark import table10
from agents.experiments.parallel import check_jobs, run_all
from agents.experiments.report import FIG3_FILE, FIG4_FILE, FIG5_FILE
from agents.experiments.resume import fold_scores_path, kept, resume_check, trained
from agents.sim import collect_flight
from estimator_service.factory import MODEL_KINDS, build_filter, load_models
from estimator_service.files import atomic_write_text, json_text
from estimator_service.flight import Flight
from estimator_service.gp.linalg import single_threaded_blas
from estimator_service.models.base import PredictionModel
from estimator_service.models.calibration import read_noise_scales, read_observation_scales
from estimator_service.progress import ProgressBar
from estimator_service.provenance import code_version, provenance
from estimator_service.tracking import (
    TrackResult,
    aggregate_rms,
    group_mean_norm,
    group_rms,
    mean_sd,
    segment_rows,
    segments,
    state_error,
    track_flight,
)
from estimator_service.training import TrainSettings, prediction_data, train_models
from estimator_service.work import part_weights, track_seconds

__all__ = ["ReproduceSettings", "reproduce", "split_folds"]


@dataclass(frozen=True)
class ReproduceSettings:
    """Sizes of the experiments; :meth:`quick` is the few-minute version.

    Attributes
    ----------
    minutes, folds
        Length of the scripted flight and the number of cross-validation blocks.
    points, pseudo, max_iter
        GP training points, sparse pseudo-inputs, optimiser iterations (paper: ~900, 50).
    track_seconds
        Length of each tracking segment of a held-out block (UKF and EKF track all of them).
    particles, pf_seconds
        The particle filters track only the first ``pf_seconds`` of each segment (an exact-GP
        PF step costs about 0.2 s with 500 particles).
    fig3_repeats, fig3_smallest, fig3_pseudo
        Fig. 3: repeats per size, the smallest random subset (sizes halve from ``points``)
        and the pseudo-input counts of the sparse curve.
    reality, reality_strength
        The simulated world (:mod:`gpbf_env.reality`; strength None: the preset's).
    calibration_folds, calibration_refit
        The models' noise calibration (:class:`~estimator_service.training.TrainSettings`).
    """

    minutes: float = 20.0
    folds: int = 4
    points: int = 900
    pseudo: int = 50
    max_iter: int = 60
    track_seconds: float = 120.0
    particles: int = 500
    pf_seconds: float = 30.0
    fig3_repeats: int = 3
    fig3_smallest: int = 50
    fig3_pseudo: tuple[int, ...] = (5, 10, 20, 50)
    kinds: tuple[str, ...] = MODEL_KINDS
    filters: tuple[str, ...] = ("ukf", "ekf", "pf")
    landmark: bool = True
    seed: int = 0
    reality: str = "lab"
    reality_strength: float | None = None
    calibration_folds: int = TrainSettings.calibration_folds
    calibration_refit: bool = TrainSettings.calibration_refit

    def train_settings(self) -> TrainSettings:
        """How every experiment here trains its models."""
        return TrainSettings(
            self.points, self.pseudo, 1, self.max_iter, 1,
            calibration_folds=self.calibration_folds, calibration_refit=self.calibration_refit,
        )  # fmt: skip

    @property
    def world(self) -> dict[str, object]:
        """Env keyword arguments of the simulated world."""
        out: dict[str, object] = {"reality": self.reality}
        if self.reality_strength is not None:
            out["reality_strength"] = self.reality_strength
        return out

    @classmethod
    def quick(cls) -> ReproduceSettings:
        return cls(
            minutes=4.0, folds=2, points=150, pseudo=20, max_iter=15, track_seconds=40.0, particles=200,
            pf_seconds=20.0, fig3_repeats=1, fig3_smallest=40, fig3_pseudo=(5, 20),
        )  # fmt: skip


def split_folds(flight: Flight, k: int) -> list[tuple[Flight, Flight]]:
    """``k`` (train, test) pairs over contiguous blocks; blocks of the training set become
    separate episodes so no transition spans a removed block."""
    blocks = np.array_split(np.arange(len(flight)), k)
    out = []
    for i, test in enumerate(blocks):
        train = np.concatenate([b for j, b in enumerate(blocks) if j != i])
        tr = flight.select(train)
        block_id = np.concatenate([np.full(len(b), j) for j, b in enumerate(blocks) if j != i])
        tr = replace(tr, episode=tr.episode * k + block_id)
        out.append((tr, flight.select(test)))
    return out


def one_step_errors(folder: Path, test: Flight, kind: str) -> dict[str, float]:
    """Table 5: one-step prediction error per state group; Table 6: observation error.

    Both as RMS and, under ``norm_<key>``, as the mean error norm (the paper's measure),
    against the flight's measured ground truth (the simulated motion capture).
    """
    pred, obs = load_models(folder, kind)
    inp, change = prediction_data([test])
    err = state_error(pred.predict(inp[:, :12], inp[:, 12:]).mean, change)
    out = group_rms(err)
    out.update({f"norm_{k}": v for k, v in group_mean_norm(err).items()})
    z = obs.observe(test.state).mean.reshape(len(test), -1, 5)
    e = z - test.z.reshape(z.shape)
    e[..., 4] = (e[..., 4] + math.pi / 2) % math.pi - math.pi / 2
    v = test.valid
    out["ellipse_position_px"] = float(np.sqrt(np.mean(np.sum(e[v][:, :2] ** 2, axis=1))))
    out["ellipse_size_px"] = float(np.sqrt(np.mean(e[v][:, 2:4] ** 2)))
    out["ellipse_angle_deg"] = float(np.degrees(np.sqrt(np.mean(e[v][:, 4] ** 2))))
    out["norm_ellipse_position_px"] = float(np.mean(np.linalg.norm(e[v][:, :2], axis=1)))
    out["norm_ellipse_size_px"] = float(np.mean(np.linalg.norm(e[v][:, 2:4], axis=1)))
    out["norm_ellipse_angle_deg"] = float(np.degrees(np.mean(np.abs(e[v][:, 4]))))
    return out


def tracking(folder: Path, test: Flight, s: ReproduceSettings, filt: str, kind: str) -> dict[str, float]:
    """Tables 7-9 and consistency: scores averaged over test segments of ``track_seconds``."""
    f = build_filter(filt, kind, folder, **({"n_particles": s.particles} if filt == "pf" else {}))
    seg, length = _segment_plan(test, s, filt)
    rows = segments(len(test), seg, length)
    with single_threaded_blas() if filt == "pf" else nullcontext():  # docs/measurements.md#one-blas-thread
        scores = [track_flight(f, test, rows=r, rng=np.random.default_rng(s.seed)).scores() for r in rows]
    out = {k: float(np.mean([sc[k] for sc in scores])) for k in scores[0]}
    out["nees_var"] /= len(scores)  # variances of the averages over the segments
    out["nis_var"] /= len(scores)
    out["aggregate_rms"] = float(np.mean([aggregate_rms(sc) for sc in scores]))
    out["steps"] = length
    return out


def _segment_plan(test: Flight, s: ReproduceSettings, filt: str) -> tuple[int, int]:
    """Rows per test segment and rows tracked of each (the PF only its first ``pf_seconds``)."""
    seg = round(s.track_seconds / test.dt)
    return seg, min(seg, round(s.pf_seconds / test.dt)) if filt == "pf" else seg


NO_LEFT_TURNS = "models_no_left_turns"  # Fig. 4's models, beside the folds'


def train_no_left_turns(out: Path, train: Flight, s: ReproduceSettings) -> None:
    """Fig. 4's models: Param and GP without the training transitions whose tail fan pushes
    left, into ``out/models_no_left_turns`` (kept when complete)."""
    reduced = out / NO_LEFT_TURNS
    if not trained(reduced):
        no_left = lambda inp: inp[:, 14] > 0.3  # noqa: E731
        train_models(
            [train], reduced, kinds=["param", "gp"], settings=s.train_settings(), seed=s.seed, exclude=no_left
        )


def plot_fig4(folder_full: Path, reduced: Path, test: Flight, path: Path) -> dict[str, float]:
    """GP-UKF yaw error with its 3-sigma band, all data vs no left-turn data; the figures."""
    import matplotlib.pyplot as plt

    from estimator_service.plots import save_figure

    left = test.control[:-1, 2] > 0.3
    res, lim = {}, 0.0
    fig, axes = plt.subplots(2, 1, figsize=(10, 6), sharex=True, sharey=True)
    for ax, (name, folder) in zip(
        axes, (("full data", folder_full), ("no left turns", reduced)), strict=True
    ):
        ukf = build_filter("ukf", "gp", folder)
        r = track_flight(ukf, test)
        t = np.arange(len(r.mean)) * test.dt
        sd = np.degrees(np.sqrt(r.cov[:, 5, 5]))
        err = np.degrees(r.error[:, 5])
        m = left[: len(t)]
        lim = max(lim, 1.2 * max(3 * sd.max(), np.abs(err).max()))
        ax.fill_between(t, -1e3, 1e3, where=m, color="0.85", lw=0)
        ax.fill_between(t, -3 * sd, 3 * sd, color="tab:blue", alpha=0.4, lw=0, label=r"$\pm 3\sigma$")
        ax.plot(t, err, "r", lw=0.8, label="estimate - truth")
        ax.set(ylabel="yaw error (deg)", title=f"GP-UKF, {name} (shaded: tail pushing left)")
        inside = np.abs(err) <= 3 * sd
        res[f"{name}: yaw std in left turns (deg)"] = float(sd[m].mean()) if m.any() else math.nan
        res[f"{name}: yaw std elsewhere (deg)"] = float(sd[~m].mean())
        res[f"{name}: truth within 3 sigma"] = float(inside.mean())
        res[f"{name}: truth within 3 sigma in left turns"] = float(inside[m].mean()) if m.any() else math.nan
        res |= _yaw_rate_figures(name, ukf.prediction, test, r, m)
    axes[0].set_ylim(-lim, lim)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time (s)")
    fig.tight_layout()
    save_figure(fig, path)
    return res


def _yaw_rate_figures(
    name: str, pred: PredictionModel, test: Flight, r: TrackResult, left: np.ndarray
) -> dict[str, float]:
    """Yaw rate in left turns: the GP-UKF's RMS error and RMS std, and the GP prediction
    model ``pred``'s one-step error (RMS, mean, lag-1 autocorrelation) and RMS predicted std of the
    yaw-rate change at the true states (deg/s). Errors that repeat from step to step build
    up in a filter that adds each step's predictive variance as independent noise.

    ``left (T,)`` marks the tracked steps of ``r``; the one-step figures use the same
    transitions, those of the rows the filter tracked (the test flight's first episode)."""
    if not left.any():
        return {}
    inp, change = prediction_data([test.select(np.arange(len(r.error) + 1))])
    out = pred.predict(inp[:, :12], inp[:, 12:])
    rms = lambda a: float(np.degrees(np.sqrt(np.mean(np.square(a)))))  # noqa: E731
    err_rms, err_mean, lag1 = persistence(np.degrees(out.mean[:, 11] - change[:, 11]), left)
    return {
        f"{name}: yaw-rate error in left turns (deg/s)": rms(r.error[left, 11]),
        f"{name}: yaw-rate std in left turns (deg/s)": rms(np.sqrt(r.cov[left, 11, 11])),
        f"{name}: one-step yaw-rate change error in left turns (deg/s)": err_rms,
        f"{name}: one-step yaw-rate change mean error in left turns (deg/s)": err_mean,
        f"{name}: one-step yaw-rate change error, lag-1 autocorrelation in left turns": lag1,
        f"{name}: one-step yaw-rate change std in left turns (deg/s)": rms(np.sqrt(out.var[left, 11])),
    }


def persistence(err: np.ndarray, mask: np.ndarray) -> tuple[float, float, float]:
    """RMS, mean and lag-1 autocorrelation of a series ``err (T,)`` over the rows in
    ``mask (T,)``; the autocorrelation pairs consecutive rows that are both in ``mask``
    (NaN with fewer than 3 such pairs)."""
    pairs = np.flatnonzero(mask[:-1] & mask[1:])
    lag1 = float(np.corrcoef(err[pairs], err[pairs + 1])[0, 1]) if pairs.size > 2 else math.nan
    e = err[mask]
    return float(np.sqrt(np.mean(e * e))), float(e.mean()), lag1


def fold_unit(
    out: Path, i: int, train: Flight, test: Flight, s: ReproduceSettings, one_step: list[str]
) -> dict:
    """Fold ``i``: its models (``out/models_fold<i>``, kept when complete), then its
    one-step errors and tracking scores, kept (:func:`kept`) so that a resumed run does not
    track the fold again (minutes at paper size)."""
    folder = out / f"models_fold{i}"
    if not trained(folder):  # complete from an earlier run in this folder
        train_models([train], folder, kinds=s.kinds, settings=s.train_settings(), seed=s.seed + i)

    def compute() -> dict:
        track = {f"{f}/{k}": tracking(folder, test, s, f, k) for f in s.filters for k in s.kinds}
        return {"table5": {k: one_step_errors(folder, test, k) for k in one_step}, "tracking": track}

    return kept(fold_scores_path(folder), compute)


def table10_unit(out: Path, s: ReproduceSettings) -> dict:
    """Table 10 (the landmark robot), kept in ``out/table10.json``; empty without ``landmark``."""
    if not s.landmark:
        return {}
    return kept(out / "table10.json", partial(table10, s.seed, particles=s.particles))


def reproduce(out: Path, s: ReproduceSettings, progress: bool = True, jobs: int = 1) -> dict:
    """Run everything and write ``report.md`` and figures into ``out``.

    The folds, Fig. 3's runs, Fig. 4's models and Table 10 are independent units
    (:mod:`agents.experiments.parallel`), run in ``jobs`` worker processes. Resumes: fold
    models already in ``out`` (``models_fold<i>``, complete ones only), their scores
    (``fold_scores/``), Fig. 3 runs already scored (``fig3_runs/``) and Table 10 are kept,
    provided ``out`` was made with the same settings."""
    check_jobs(jobs)
    resume_check(out, asdict(s))
    t0, code = time.perf_counter(), code_version()  # the code that runs, not the checkout at the end
    flight = collect_flight(s.minutes * 60, seed=s.seed, env_kwargs=s.world)
    folds = split_folds(flight, s.folds)
    one_step = [k for k in ("param", "gp", "egp") if k in s.kinds]
    units: list = [
        partial(fold_unit, out, i, train, test, s, one_step) for i, (train, test) in enumerate(folds)
    ]
    fig3 = _fig3_runs(folds[0], s, out)
    units += [*fig3, partial(train_no_left_turns, out, folds[0][0], s), partial(table10_unit, out, s)]
    weights = _unit_seconds(out, folds, fig3, s)
    kept = [i for i, w in enumerate(weights) if w == KEPT_S]  # kept whole from an earlier run
    with ProgressBar("reproduce", unit="unit", enabled=progress, weights=weights, done=kept) as bar:
        done = run_all(units, jobs, lambda i: bar.advance(index=i))
    fold_scores, t10 = done[: len(folds)], done[-1]
    results = {
        "fig3": _plot_fig3(fig3, done[len(folds) : len(folds) + len(fig3)], out),
        "settings": asdict(s),
        "table5_6": {k: mean_sd([f["table5"][k] for f in fold_scores]) for k in one_step},
        "tracking": {k: mean_sd([f["tracking"][k] for f in fold_scores]) for k in fold_scores[0]["tracking"]},
        "fig4": plot_fig4(out / "models_fold0", out / NO_LEFT_TURNS, folds[0][1], out / FIG4_FILE),
        "fig5": fig5(out / "models_fold0", folds[0][1], out / FIG5_FILE)
        if {"gp", "hetgp"} <= set(s.kinds)
        else {},
    }
    results["table10"] = {k: v for k, v in t10.items() if not k.startswith("spread")}
    results["table10_spread"] = {k: v for k, v in t10.items() if k.startswith("spread")}
    folders = [out / f"models_fold{i}" for i in range(len(folds))]
    results["noise_scales"] = [read_noise_scales(f) for f in folders]
    results["observation_scales"] = [
        {k: v.tolist() for k, v in read_observation_scales(f).items()} for f in folders
    ]
    results["wall_s"] = time.perf_counter() - t0
    results["provenance"] = provenance(results["wall_s"], code=code)
    from agents.experiments.report import verdicts, write_report

    results.update(verdicts(results))
    atomic_write_text(out / "results.json", json_text(results, indent=2))

    write_report(out, results)
    return results


KEPT_S = 0.5  # a unit whose results the folder keeps: read back
TABLE10_PARTICLE_S = 0.05  # Table 10's seconds per particle (docs/measurements.md#progress-weights)


def _unit_seconds(out: Path, folds: list, fig3: list, s: ReproduceSettings) -> list[float]:
    """Each unit's estimated seconds (:mod:`estimator_service.work`), in the units' order, so
    the progress display's share done and ETA follow time; what ``out`` keeps is nearly free."""
    ts = s.train_settings()

    def fold(i: int, train: Flight, test: Flight) -> float:
        folder = out / f"models_fold{i}"
        total = 0.0 if trained(folder) else sum(part_weights([train], s.kinds, ts))
        if not fold_scores_path(folder).exists():
            for f in s.filters:
                steps = segment_rows(len(test), *_segment_plan(test, s, f))
                total += sum(track_seconds([train], k, ts, f, steps, s.particles) for k in s.kinds)
        return total

    train0 = folds[0][0]
    left = 0.0 if trained(out / NO_LEFT_TURNS) else sum(part_weights([train0], ["param", "gp"], ts))
    t10 = TABLE10_PARTICLE_S * s.particles if s.landmark and not (out / "table10.json").exists() else 0.0
    units = [fold(i, *f) for i, f in enumerate(folds)] + [run.seconds() for run in fig3] + [left, t10]
    return [KEPT_S + w for w in units]


def _fig3_runs(fold: tuple[Flight, Flight], s: ReproduceSettings, out: Path) -> list:
    """Paper Fig. 3's runs on the first fold, kept in ``out/fig3_runs``."""
    from agents.experiments.fig3 import fig3_runs, size_levels

    return fig3_runs(
        *fold, s.train_settings(), points=size_levels(s.points, s.fig3_smallest),
        pseudo=[m for m in s.fig3_pseudo if m <= s.points], repeats=s.fig3_repeats,
        track_seconds=s.track_seconds, seed=s.seed, cache=out / "fig3_runs",
    )  # fmt: skip


def _plot_fig3(runs: list, results: list[dict], out: Path) -> dict:
    """Fig. 3's table from its runs; writes ``fig3_training_points.png``."""
    from agents.experiments.fig3 import fig3_table, plot_data_sparsity

    res = fig3_table(runs, results)
    plot_data_sparsity(res, out / FIG3_FILE)
    return res
