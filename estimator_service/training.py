"""Train every model kind from recorded flights and save them as the factory expects.

Prediction data (paper eq. 12): ``[x_k, u_k] -> x_{k+1} - x_k`` (angle changes wrapped).
Observation data (eq. 13), one model per sensor: ``x_k -> z_k`` over the readings that
sensor delivered. Both are subsampled to ``n_points`` (paper: ~900).

The ``param`` kind is the system's parametric model family (the blimp's ODE and camera
model); the ``egp`` and ``hetgp`` kinds model its residual (eq. 16), so a system without
one trains ``gp`` and ``sparse`` only. Every GP sees the state angles listed in the
system's ``circle_inputs`` as ``(cos, sin)`` (the blimp: the yaw, which wraps at +-pi), and
the observation GPs other than the enhanced ones regress a sensor's angle output (the
ellipse orientation, period pi) as a unit vector: see :mod:`estimator_service.gp.circular`.
The folder is written through :mod:`estimator_service.store`: whole or not at all.
"""

from __future__ import annotations

import json
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from estimator_service.crossfit import calibration_folds, cross_fit
from estimator_service.factory import (
    ENHANCED_KINDS,
    MODEL_KINDS,
    PARAMETRIC_FILE,
    Parametric,
    load_parametric,
    observation_files,
    observation_parts,
)
from estimator_service.files import atomic_write_text
from estimator_service.flight import Flight
from estimator_service.gp import (
    Progress,
    fit_circular,
    fit_enhanced,
    fit_exact,
    fit_hetero,
    fit_sparse,
    load_innermost_gp,
    save_gp,
)
from estimator_service.models.calibration import write_process_ceiling
from estimator_service.preflight import PreflightWarning, preflight
from estimator_service.store import writing
from estimator_service.system import Sensor, System, wrap_columns
from estimator_service.user_models import (
    USER_MODELS_FILE,
    fit_user_models,
    load_user_models,
    save_user_models,
    user_models,
)

#: per kind and model part, each output's claimed noise std beside its floor (see _claimed_std)
NOISE_FILE = "noise.json"

__all__ = [
    "NOISE_FILE",
    "TrainSettings",
    "available_kinds",
    "prediction_data",
    "train_models",
]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TrainSettings:
    """How hard to train.

    Attributes
    ----------
    n_points
        Training points per GP after subsampling (paper: ~900).
    n_pseudo
        Pseudo-inputs of the sparse GPs (paper: 50).
    restarts, max_iter
        Hyperparameter optimisation effort of the exact GPs.
    hetero_iterations
        EM-like rounds of the heteroscedastic GPs.
    sparse_iter
        Optimiser iterations of the sparse GPs (hyperparameters and ``n_pseudo * d``
        pseudo-input coordinates). More is not better here: on a held-out blimp block the
        sparse GP-EKF scored aggregate RMS 14.6, 12.3, 13.2 and 13.3 after 60, 120, 200
        and 500 iterations while the marginal likelihood kept improving.
    calibration_seconds, calibration_folds, calibration_refit
        Noise calibration by cross-fitting (:mod:`estimator_service.crossfit`; 0 seconds
        skips it). Folds (:func:`~estimator_service.crossfit.calibration_folds`): with one
        flight, ``calibration_folds`` blocks of ``calibration_seconds`` spread over it; with
        several, each of the first ``calibration_folds`` flights held out whole in turn. Each
        fold's models are fitted without its rows, which then set the observation-noise
        scales (:func:`~estimator_service.calibrate.calibrate_observation`) and the one-step
        process-noise scales (:func:`~estimator_service.calibrate.calibrate_process`); the
        held-out log-likelihood over all the folds' rows chooses the final scales
        (:func:`~estimator_service.matching.calibrate_by_likelihood`); the saved models are
        trained on everything. With ``calibration_refit`` each fold learns its own hyperparameters
        (``calibration_folds`` extra fits); without (the default), it keeps the final
        models' and is only conditioned on its data (no optimisation: a few per cent of a
        fit). Chosen by a rule fixed before the run, on simulator flights no report uses
        (measured: docs/measurements.md#calibration-folds).
    hyper_points, polish_iter
        Exact and heteroscedastic GPs learn hyperparameters on a random subset of
        ``hyper_points`` points, then polish them for ``polish_iter`` iterations on all
        (None: all points from the start); see :func:`~estimator_service.gp.fit_exact`.
    """

    n_points: int = 900
    n_pseudo: int = 50
    restarts: int = 2
    max_iter: int = 100
    hetero_iterations: int = 2
    sparse_iter: int = 120
    hyper_points: int | None = 300
    polish_iter: int = 15
    calibration_seconds: float = 120.0
    calibration_folds: int = 4
    calibration_refit: bool = False


def prediction_data(flights: Sequence[Flight]) -> tuple[FloatArray, FloatArray]:
    """Inputs ``[x, u] (T, n + k)`` and targets ``x' - x (T, n)`` from all transitions."""
    xs, us, xn = zip(*(f.transitions() for f in flights), strict=True)
    x, u, x_next = np.concatenate(xs), np.concatenate(us), np.concatenate(xn)
    return np.concatenate([x, u], axis=1), flights[0].system.state_error(x_next, x)


def observation_data(flights: Sequence[Flight], sensor: int) -> tuple[FloatArray, FloatArray]:
    """States ``(T, n)`` and readings ``(T, size)`` where ``sensor`` delivered one."""
    xs, zs = zip(*(f.readings(sensor) for f in flights), strict=True)
    return np.concatenate(xs), np.concatenate(zs)


def available_kinds(system: System) -> tuple[str, ...]:
    """The model kinds a system can train: all five with a parametric model family, else
    ``gp`` and ``sparse``."""
    if system.has_parametric:
        return MODEL_KINDS
    return tuple(k for k in MODEL_KINDS if k != "param" and k not in ENHANCED_KINDS)


def _check_flights(flights: Sequence[Flight], kinds: Sequence[str]) -> System:
    if not flights:
        raise ValueError("no flights to train on")
    system = flights[0].system
    for i, f in enumerate(flights[1:], 1):
        if f.system != system:
            raise ValueError(f"flight {i} describes another system than flight 0 ({f.system} vs {system})")
    unknown = set(kinds) - set(MODEL_KINDS)
    if unknown:
        raise ValueError(f"unknown model kinds {sorted(unknown)}; choose from {MODEL_KINDS}")
    unavailable = set(kinds) - set(available_kinds(system))
    if unavailable:
        raise ValueError(
            f"model kinds {sorted(unavailable)} need a parametric model, which system {system.name!r} "
            f"has not; choose from {available_kinds(system)}"
        )
    if any(sum(p > 0 for p in s.periods) > 1 for s in system.sensors):
        raise ValueError("a sensor may have at most one angle output")
    if sum(len(f.transition_rows()) for f in flights) < 2:
        raise ValueError("the flights hold fewer than 2 transitions: record longer")
    return system


def _subsample(n: int, k: int, rng: np.random.Generator) -> NDArray[np.intp]:
    return np.sort(rng.choice(n, size=min(n, k), replace=False))


def _fitter(kind: str, s: TrainSettings, rng: np.random.Generator, cb) -> Callable:
    common = {"rng": rng, "callback": cb}
    exact = {"max_iter": s.max_iter, "hyper_points": s.hyper_points, "polish_iter": s.polish_iter}
    if kind in ("gp", "egp"):
        return lambda x, y: fit_exact(x, y, restarts=s.restarts, **exact, **common)
    if kind == "hetgp":
        return lambda x, y: fit_hetero(x, y, iterations=s.hetero_iterations, restarts=1, **exact, **common)
    return lambda x, y: fit_sparse(x, y, n_pseudo=min(s.n_pseudo, len(x)), max_iter=s.sparse_iter, **common)


def train_models(
    flights: Sequence[Flight],
    out_dir: str | Path,
    *,
    kinds: Sequence[str] | None = None,
    settings: TrainSettings = TrainSettings(),
    seed: int = 0,
    on_progress: Callable[[str, Progress | None], None] | None = None,
    exclude: Callable[[FloatArray], NDArray[np.bool_]] | None = None,
) -> dict[str, float]:
    """Fit and save the requested model kinds (default: all the flights' system can train,
    :func:`available_kinds`); returns training seconds per kind.

    ``exclude(inputs) -> mask`` drops prediction training rows (e.g. tail pushing left,
    paper Fig. 4). ``on_progress(label, progress)`` reports optimiser iterations, and with
    ``progress`` None that the unit of work ``label`` is done (as many as
    :func:`~estimator_service.work.part_weights` weighs: the fits, then each fold's
    calibration, then each kind's noise choice).
    Randomness: the training subsets come from one stream of ``seed`` and each kind's
    optimiser from its own, so a kind's models do not depend on which other kinds are
    trained beside it. ``out_dir`` is replaced whole when training succeeds and left as it
    was when it fails.
    """
    kinds = available_kinds(flights[0].system) if kinds is None and flights else kinds
    system = _check_flights(flights, kinds or ())
    folds = calibration_folds(flights, settings.calibration_seconds, settings.calibration_folds)
    for message in preflight(flights, system, folds):
        warnings.warn(message, PreflightWarning, stacklevel=2)
    with writing(out_dir, system) as out:
        return _train_into(out, flights, system, kinds, settings, seed, on_progress, exclude, folds)


def _train_into(out: Path, flights, system: System, kinds, settings: TrainSettings, seed: int,
                on_progress, exclude, folds) -> dict[str, float]:  # fmt: skip
    timings = _fit_models(out, flights, system, kinds, settings, seed, on_progress, exclude)
    if folds:
        t0 = time.perf_counter()

        def fit(folder: Path, fold_flights: list[Flight]) -> None:
            reuse = None if settings.calibration_refit else out
            report = None  # conditioned on the fold's data only: too quick to count
            if settings.calibration_refit and on_progress is not None:
                report = lambda kind, p: on_progress(f"calibration: {kind} refitted", p)  # noqa: E731
            _fit_models(folder, fold_flights, system, kinds, settings, seed, report, exclude, reuse=reuse)

        tick = None if on_progress is None else lambda label: on_progress(label, None)
        cross_fit(out, flights, system, kinds, folds, fit, tick=tick)
        timings["calibration"] = time.perf_counter() - t0
    return timings


def _fit_models(out: Path, flights, system: System, kinds, settings: TrainSettings, seed: int,
                on_progress, exclude, reuse: Path | None = None) -> dict[str, float]:  # fmt: skip
    """Fit and save every kind in ``kinds`` on all of ``flights``; seconds per kind. With
    ``reuse`` (a folder of models of the same kinds) the GPs keep that folder's
    hyperparameters and are only conditioned on ``flights``' data (no optimisation). The
    flights' state variances are stored as the process-variance ceiling
    (:mod:`estimator_service.models.calibration`), and (without ``reuse``) the noise each
    model claims in ``noise.json``."""
    write_process_ceiling(out, np.concatenate([f.state for f in flights]))
    rng = np.random.default_rng([seed, 0])
    timings: dict[str, float] = {}
    n = system.state_dim
    param = None
    inp, change = prediction_data(flights)
    all_obs = observation_sets(flights, system)
    if system.has_parametric and any(k == "param" or k in ENHANCED_KINDS for k in kinds):
        t0 = time.perf_counter()
        param = _fit_parametric(out, flights, system, (inp, change), all_obs)
        timings["param"] = time.perf_counter() - t0
    noise: dict[str, dict] = {}
    if param is not None:
        noise["param"] = _parametric_std(out, system, inp)  # the rows the models were fitted on
    if exclude is not None:
        keep = ~exclude(inp)
        inp, change = inp[keep], change[keep]
    rows = _subsample(len(inp), settings.n_points, rng)
    obs_sets = {}
    for part, (xs, zs) in all_obs.items():
        sel = _subsample(len(xs), settings.n_points, rng)
        obs_sets[part] = (xs[sel], zs[sel])
    angles = tuple(system.circle_inputs or ())
    for kind in (k for k in kinds if k != "param"):
        t0 = time.perf_counter()

        def cb(p: Progress, kind: str = kind) -> None:
            if on_progress:
                on_progress(kind, p)

        learn = _fitter(kind, settings, np.random.default_rng([seed, 1 + MODEL_KINDS.index(kind)]), cb)

        def base_for(name: str, learn: Callable = learn) -> Callable:
            return learn if reuse is None else _conditioner(reuse / name)

        def fit(x: FloatArray, y: FloatArray, base: Callable) -> object:
            return fit_circular(x, y, base, angle_inputs=angles)

        x, y = inp[rows], change[rows]
        name = f"prediction_{kind}.npz"
        if kind in ENHANCED_KINDS:
            mean = param.change
            pred = fit_enhanced(x, y, lambda q, mean=mean: mean(q[:, :n], q[:, n:]), fit, base=base_for(name))
        else:
            pred = fit(x, y, base_for(name))
        save_gp(pred, out / name)
        report = reuse is None  # a calibration fold's models are scored, not reported
        claimed = (
            {"prediction": _claimed_std(pred, x, system.state, system.process_noise_floor)} if report else {}
        )
        for part, name in observation_files(system, kind).items():
            xs, zs = obs_sets[part]
            sensor = _part_sensor(system, part)
            if kind in ENHANCED_KINDS:
                mean = param.sensor_means[part]
                fx = mean(xs)  # the residual of an angle output on its circle: z - f(x) wrapped
                obs = fit_enhanced(
                    xs, fx + wrap_columns(zs - fx, np.asarray(sensor.periods)), mean, fit, base=base_for(name)
                )
            else:
                obs = _fit_sensor(xs, zs, base_for(name), angles, sensor.periods)
            save_gp(obs, out / name)
            if report:
                claimed[part] = _claimed_std(obs, xs, sensor.outputs, sensor.noise_floor)
        noise[kind] = claimed
        timings[kind] = time.perf_counter() - t0
        if on_progress:
            on_progress(kind, None)
    atomic_write_text(out / NOISE_FILE, json.dumps(noise, indent=1))
    return timings


def _claimed_std(model, x: FloatArray, names: Sequence[str], floor: Sequence[float]) -> dict[str, dict]:
    """``{output: {"std": median predictive std at the training inputs, "floor": floor}}``:
    the noise a model claims beside the least the description allows (applied when filtering)."""
    return _named_std(np.median(np.sqrt(model.predict(x, return_var=True).var), axis=0), names, floor)


def _named_std(std: FloatArray, names: Sequence[str], floor: Sequence[float]) -> dict[str, dict]:
    return {n: {"std": float(s), "floor": float(f)} for n, s, f in zip(names, std, floor, strict=True)}


def _parametric_std(out: Path, system: System, inp: FloatArray) -> dict[str, dict]:
    """The user's fitted parametric models' noise std (their residuals', at least the floor;
    with a noise shape, the median over the prediction inputs ``inp (T, n + k)``) as
    :func:`_claimed_std` reports it; empty for the blimp's models."""
    if system.parametric is not None:
        return {}
    fitted = load_user_models(out / USER_MODELS_FILE, system)
    n = system.state_dim
    pred = user_models(fitted, system)[0].predict(inp[:, :n], inp[:, n:]).var
    parts = {"prediction": (np.median(pred, axis=0), system.state, system.process_noise_floor)}
    for part, ks in observation_parts(system).items():
        sensor = system.sensors[ks[0]]
        parts[part] = (fitted.sensor_types[sensor.type].noise_var, sensor.outputs, sensor.noise_floor)
    return {part: _named_std(np.sqrt(var), names, floor) for part, (var, names, floor) in parts.items()}


def _part_sensor(system: System, part: str) -> Sensor:
    """The sensor (or the first sensor of the type) an observation part models."""
    return system.sensors[observation_parts(system)[part][0]]


def observation_sets(flights: Sequence[Flight], system: System) -> dict[str, tuple[FloatArray, FloatArray]]:
    """Training inputs and readings of every observation part
    (:func:`~estimator_service.factory.observation_parts`): the states of its sensors'
    readings with each sensor's constants appended ``(T, n + c)`` (``c = 0`` for a sensor
    without a type) and the readings ``(T, size)``, sensor by sensor."""
    sets = {}
    for part, ks in observation_parts(system).items():
        xs, zs = [], []
        for k in ks:
            x, z = observation_data(flights, k)
            xs.append(np.concatenate([x, np.tile(system.sensors[k].constants, (len(x), 1))], axis=1))
            zs.append(z)
        sets[part] = (np.concatenate(xs), np.concatenate(zs))
    return sets


def _fit_parametric(
    out: Path, flights: Sequence[Flight], system: System, transitions: tuple[FloatArray, FloatArray],
    obs_sets: dict[str, tuple[FloatArray, FloatArray]],
) -> Parametric:  # fmt: skip
    """Fit the system's parametric models to all ``flights`` (their ``transitions``, inputs
    and changes of :func:`prediction_data`, and ``obs_sets`` of :func:`observation_sets`),
    save them into ``out`` and return them as the factory loads them (the blimp's ODE and
    camera model, or the user's models of :mod:`estimator_service.user_models`)."""
    n, (inp, change) = system.state_dim, transitions
    x, u = inp[:, :n], inp[:, n:]
    if system.parametric == "blimp":
        from estimator_service.blimp import fit_parametric, save_parametric

        save_parametric(*fit_parametric(flights, x, u, x + change), out / PARAMETRIC_FILE)
    else:
        readings = {
            _part_sensor(system, part).type: (xs[:, :n], xs[:, n:], zs) for part, (xs, zs) in obs_sets.items()
        }
        save_user_models(fit_user_models(system, (x, u, x + change), readings), out / USER_MODELS_FILE)
    return load_parametric(out, system)


def _conditioner(path: Path) -> Callable[[FloatArray, FloatArray], object]:
    """A base fitter that conditions the innermost GP saved at ``path`` on new data, keeping
    its hyperparameters (:meth:`~estimator_service.gp.ExactGP.conditioned`)."""
    return load_innermost_gp(path).conditioned


def _fit_sensor(xs: FloatArray, zs: FloatArray, base: Callable, angles: tuple[int, ...],
                periods: tuple[float, ...]) -> object:  # fmt: skip
    """A sensor's observation GP; its angle output (if any) regressed as a unit vector."""
    ang = [i for i, p in enumerate(periods) if p > 0]
    if not ang:
        return fit_circular(xs, zs, base, angle_inputs=angles)
    return fit_circular(xs, zs, base, angle_inputs=angles, angle_output=ang[0], period=periods[ang[0]])
