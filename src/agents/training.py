"""Train every model kind from recorded flights and save them as the factory expects.

Prediction data (paper eq. 12): ``[x_k, u_k] -> x_{k+1} - x_k`` (Euler-angle changes
wrapped). Observation data (eq. 13), one model per camera: ``x_k -> ellipse_k`` over the
frames that camera delivered. Both are subsampled to ``n_points`` (paper: ~900).

The ``egp`` and ``hetgp`` kinds model the residual of the parametric models (eq. 16).
Every GP sees the yaw as ``(cos, sin)`` (it wraps at +-pi; roll and pitch stay small), and
the observation GPs other than the enhanced one regress the ellipse orientation (period pi)
as a unit vector: see :mod:`estimator_service.gp.circular`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from agents.calibrate import (
    ELLIPSE_ANGLE,
    calibrate_noise,
    calibrate_observation,
    calibration_rows,
    without_frames,
)
from agents.recorder import Flight
from agents.tracking import wrap_angle
from estimator_service.factory import ENHANCED_KINDS, MODEL_KINDS, save_parametric
from estimator_service.gp import (
    Progress,
    fit_circular,
    fit_enhanced,
    fit_exact,
    fit_hetero,
    fit_sparse,
    save_gp,
)
from estimator_service.models.blimp import BlimpODE, fit_blimp_ode
from estimator_service.models.camera import CameraModel, PinholeCalibration, fit_camera_model

__all__ = ["TrainSettings", "calibrations", "prediction_data", "train_models"]

FloatArray = NDArray[np.float64]
YAW = (5,)  # angle inputs that wrap


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
    calibration_seconds
        Length of the training-flight stretch on which each kind's noise is calibrated (0
        skips calibration): its frames (at most a quarter of the flight) are kept out of
        every observation model and set the observation-noise scales
        (:func:`calibrate_observation`), then the process-noise scale is chosen on it
        (:func:`calibrate_noise`).
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
    calibration_seconds: float = 60.0


def prediction_data(flights: Sequence[Flight]) -> tuple[FloatArray, FloatArray]:
    """Inputs ``[x, u] (T, 15)`` and targets ``x' - x (T, 12)`` from all transitions."""
    xs, us, xn = zip(*(f.transitions() for f in flights), strict=True)
    x, u, x_next = np.concatenate(xs), np.concatenate(us), np.concatenate(xn)
    change = x_next - x
    change[:, 3:6] = wrap_angle(change[:, 3:6])
    return np.concatenate([x, u], axis=1), change


def observation_data(flights: Sequence[Flight], camera: int) -> tuple[FloatArray, FloatArray]:
    """States ``(T, 12)`` and ellipses ``(T, 5)`` where ``camera`` delivered a frame."""
    xs = [f.state[f.valid[:, camera]] for f in flights]
    zs = [f.ellipses[f.valid[:, camera], camera] for f in flights]
    return np.concatenate(xs), np.concatenate(zs)


def calibrations(flight: Flight) -> tuple[PinholeCalibration, ...]:
    """The cameras' known calibration from a flight's metadata (distortion is ignored)."""
    return tuple(
        PinholeCalibration(
            np.array(c["position"]),
            np.array(c["rotation"]),
            float(c["focal"]),
            (float(c["principal_point"][0]), float(c["principal_point"][1])),
        )
        for c in flight.metadata["cameras"]
    )


def _subsample(n: int, k: int, rng: np.random.Generator) -> NDArray[np.intp]:
    return np.sort(rng.choice(n, size=min(n, k), replace=False))


def train_parametric(flights: Sequence[Flight]) -> tuple[BlimpODE, CameraModel]:
    """The parametric ODE (all transitions) and camera model (all frames)."""
    inp, change = prediction_data(flights)
    params = flights[0].metadata["params"]
    x = inp[:, :12]
    ode = fit_blimp_ode(
        x,
        inp[:, 12:],
        x + change,
        mass=params["mass"],
        tail_arm=params["tail_arm"],
        dt=flights[0].metadata["dt"],
    )
    state = np.concatenate([f.state for f in flights])
    z = np.concatenate([f.ellipses.reshape(len(f), -1) for f in flights])
    valid = np.concatenate([f.valid for f in flights])
    return ode, fit_camera_model(calibrations(flights[0]), state, z, valid)


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
    kinds: Sequence[str] = MODEL_KINDS,
    settings: TrainSettings = TrainSettings(),
    seed: int = 0,
    on_progress: Callable[[str, Progress | None], None] | None = None,
    exclude: Callable[[FloatArray], NDArray[np.bool_]] | None = None,
) -> dict[str, float]:
    """Fit and save the requested model kinds; returns training seconds per kind.

    ``exclude(inputs) -> mask`` drops prediction training rows (e.g. tail pushing left,
    paper Fig. 4). ``on_progress(label, progress)`` reports optimiser iterations.
    Randomness: the training subsets come from one stream of ``seed`` and each kind's
    optimiser from its own, so a kind's models do not depend on which other kinds are
    trained beside it.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    unknown = set(kinds) - set(MODEL_KINDS)
    if unknown:
        raise ValueError(f"unknown model kinds {sorted(unknown)}; choose from {MODEL_KINDS}")
    rng = np.random.default_rng([seed, 0])
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    held_out = calibration_rows(flights[0], settings.calibration_seconds)
    framed = [without_frames(flights[0], held_out), *flights[1:]]  # for the observation models
    ode, cam = train_parametric(framed)
    save_parametric(ode, cam, out / "parametric.npz")
    timings["param"] = time.perf_counter() - t0
    inp, change = prediction_data(flights)
    if exclude is not None:
        keep = ~exclude(inp)
        inp, change = inp[keep], change[keep]
    rows = _subsample(len(inp), settings.n_points, rng)
    obs_sets = []
    for k in range(flights[0].n_cameras):
        xs, zs = observation_data(framed, k)
        sel = _subsample(len(xs), settings.n_points, rng)
        obs_sets.append((xs[sel], zs[sel]))
    for kind in (k for k in kinds if k != "param"):
        t0 = time.perf_counter()

        def cb(p: Progress, kind: str = kind) -> None:
            if on_progress:
                on_progress(kind, p)

        kind_rng = np.random.default_rng([seed, 1 + MODEL_KINDS.index(kind)])
        base = _fitter(kind, settings, kind_rng, cb)

        def fit(x: FloatArray, y: FloatArray, base: Callable = base) -> object:
            return fit_circular(x, y, base, angle_inputs=YAW)

        def fit_obs(x: FloatArray, y: FloatArray, base: Callable = base) -> object:
            return fit_circular(x, y, base, angle_inputs=YAW, angle_output=ELLIPSE_ANGLE, period=np.pi)

        x, y = inp[rows], change[rows]
        if kind in ENHANCED_KINDS:
            pred = fit_enhanced(x, y, lambda q: ode.change(q[:, :12], q[:, 12:]), fit)
        else:
            pred = fit(x, y)
        save_gp(pred, out / f"prediction_{kind}.npz")
        for k, (xs, zs) in enumerate(obs_sets):
            if kind in ENHANCED_KINDS:
                obs = fit_enhanced(xs, zs, lambda q, k=k: cam.mean(q)[:, 5 * k : 5 * k + 5], fit)
            else:
                obs = fit_obs(xs, zs)
            save_gp(obs, out / f"observation_{kind}_cam{k}.npz")
        timings[kind] = time.perf_counter() - t0
        if on_progress:
            on_progress(kind, None)
    if settings.calibration_seconds > 0:
        t0 = time.perf_counter()
        calibrate_observation(flights[0], out, kinds, rows=held_out)
        calibrate_noise(flights[0], out, kinds, seconds=settings.calibration_seconds)
        timings["calibration"] = time.perf_counter() - t0
    return timings
