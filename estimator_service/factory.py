"""Build any (filter, model kind) pair from a model folder: the paper's 3 x 5 grid.

A model folder (written and checked by :mod:`estimator_service.store`) holds
``system.json``, for each GP kind ``k`` in ``gp``, ``egp``, ``hetgp``, ``sparse``
``prediction_k.npz`` and one ``observation_k_cam<i>.npz`` per sensor (or one
``observation_k.npz`` for all; see :mod:`estimator_service.gp.io`), and, for a system
with a parametric model family (the blimp), ``parametric.npz`` with its prediction and
observation models, which the enhanced kinds use as their mean functions.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from estimator_service.filters import EKF, PF, UKF, GaussianBelief
from estimator_service.filters.adaptive import ADAPT_RATE
from estimator_service.gp import load_gp
from estimator_service.models.base import ObservationModel, PredictionModel
from estimator_service.models.calibration import (
    NoiseScaledObservation,
    NoiseScaledPrediction,
    read_nis_reference,
    read_noise_scales,
    read_observation_scales,
    read_process_ceiling,
    read_process_scales,
)
from estimator_service.models.gp_models import (
    GPObservationModel,
    GPPredictionModel,
    StackedObservationModel,
)
from estimator_service.store import check_folder, read_system
from estimator_service.system import System

__all__ = [
    "FILTER_KINDS",
    "MODEL_KINDS",
    "adaptation_defaults",
    "apply_calibration",
    "build_filter",
    "load_models",
    "make_filter",
    "warm_up",
]

FILTER_KINDS = ("ukf", "ekf", "pf")
MODEL_KINDS = ("param", "gp", "egp", "hetgp", "sparse")
#: kinds whose GPs model the residual of the parametric models (paper eq. 16); the
#: heteroscedastic GP is one of them, as the paper's Tables 7-8 rank it above the EGP.
ENHANCED_KINDS = ("egp", "hetgp")
PARAMETRIC_FILE = "parametric.npz"


def _parametric(folder: Path, system: System) -> tuple[PredictionModel, ObservationModel]:
    """The system's parametric models (the blimp's ODE and camera model)."""
    if system.parametric != "blimp":
        raise ValueError(
            f"system {system.name!r} has no parametric model family: the 'param', 'egp' and "
            "'hetgp' kinds need one; use 'gp' or 'sparse'"
        )
    from estimator_service.blimp import load_parametric

    return load_parametric(folder / PARAMETRIC_FILE)


def load_models(
    model_dir: str | os.PathLike[str], kind: str, *, calibrated: bool = True, check: bool = True
) -> tuple[PredictionModel, ObservationModel]:
    """Prediction and observation models of ``kind`` (one of :data:`MODEL_KINDS`).

    With ``calibrated`` the prediction and observation noise are scaled by the folder's
    ``calibration.json`` entries for ``kind`` where there are any (see
    :mod:`estimator_service.models.calibration`). ``check`` refuses an incomplete or mixed
    folder (:func:`estimator_service.store.check_folder`); training turns it off for the
    folder it is still writing.
    """
    if kind not in MODEL_KINDS:
        raise ValueError(f"model kind must be one of {MODEL_KINDS}, got {kind!r}")
    folder = Path(model_dir)
    if check:
        check_folder(folder)
    system = read_system(folder)
    n = system.state_dim
    param = _parametric(folder, system) if kind == "param" or kind in ENHANCED_KINDS else None
    if kind == "param":
        pred, obs = param
    else:
        extra_p = {}
        if param is not None:
            ode = param[0]
            extra_p = {"mean_function": lambda q: ode.change(q[:, :n], q[:, n:])}
        pred = GPPredictionModel(load_gp(folder / f"prediction_{kind}.npz", **extra_p), n)
        obs = _observation(folder, kind, system, None if param is None else param[1])
    return apply_calibration(folder, kind, pred, obs) if calibrated else (pred, obs)


def apply_calibration(
    folder: str | os.PathLike[str], kind: str, pred: PredictionModel, obs: ObservationModel,
    *, process: bool = True,
) -> tuple[PredictionModel, ObservationModel]:  # fmt: skip
    """``pred`` and ``obs`` with the noise scales of ``folder/calibration.json`` for ``kind``
    (where there are any) and the process-variance ceiling (where there is one);
    ``process=False`` leaves the prediction noise as it is."""
    scale = read_noise_scales(folder).get(kind, 1.0) if process else 1.0
    if process and kind in (per_output := read_process_scales(folder)):
        scale = scale * per_output[kind]
    ceiling = read_process_ceiling(folder, pred.state_dim) if process else None
    obs_scale = read_observation_scales(folder).get(kind)
    plain = ceiling is None and np.all(np.asarray(scale) == 1.0)
    return (
        pred if plain else NoiseScaledPrediction(pred, scale, ceiling),
        obs if obs_scale is None else NoiseScaledObservation(obs, obs_scale),
    )


def _observation(folder: Path, kind: str, system: System, cam: ObservationModel | None) -> ObservationModel:
    """One file for all sensors, or one ``observation_<kind>_cam<k>.npz`` per sensor; ``cam``
    (the parametric observation model) is the enhanced kinds' mean function."""
    single = folder / f"observation_{kind}.npz"
    if single.exists():
        return GPObservationModel(load_gp(single, **({"mean_function": cam.mean} if cam is not None else {})))
    parts = []
    for k in range(system.n_sensors):
        sl = system.sensor_slice(k)
        extra = {"mean_function": lambda x, sl=sl: cam.mean(x)[:, sl]} if cam is not None else {}
        parts.append(GPObservationModel(load_gp(folder / f"observation_{kind}_cam{k}.npz", **extra)))
    return StackedObservationModel(tuple(parts))


# Regularised resampling with the Kalman-updated covariance of the predicted cloud. On the
# committed seed-0 full run's held-out segments (8 x 30 s, 500 particles) the aggregate RMS
# with the weighted-posterior kernel was GP 24.9, EGP 20.7, hetGP 27.2, sparse 15.3,
# Param 17.0, and with the Kalman kernel GP 13.3, EGP 10.4, hetGP 9.9, sparse 11.8,
# Param 16.2: the weighted covariance collapses whenever one particle takes almost all
# the weight, and the cloud then cannot follow the truth.
_PF_DEFAULTS: dict[str, object] = {"roughen": 1.0, "roughen_cov": "kalman"}


def make_filter(
    kind: str, prediction: PredictionModel, observation: ObservationModel, *,
    system: System | None = None, **options: object,
) -> EKF | UKF | PF:  # fmt: skip
    """A filter of ``kind`` (``ekf``, ``ukf``, ``pf``) over the given models.

    ``system`` sets the angle handling (``wrapping``) and which states an adaptive filter
    inflates (``adapt_states``, its ``disturbed`` components); ``options`` go to the filter
    (e.g. ``alpha`` for the UKF, ``n_particles`` for the PF). An EKF or UKF adapts its
    process noise at :data:`~estimator_service.filters.adaptive.ADAPT_RATE` unless
    ``adapt_rate`` says otherwise (0: the paper's filter).
    """
    if kind not in FILTER_KINDS:
        raise ValueError(f"filter kind must be one of {FILTER_KINDS}, got {kind!r}")
    cls = {"ekf": EKF, "ukf": UKF, "pf": PF}[kind]
    if kind == "pf" and options.get("adapt_rate"):
        raise ValueError("adapt_rate: the adaptive process noise is for the EKF and UKF, not the PF")
    if kind != "pf":
        options.setdefault("adapt_rate", ADAPT_RATE)
    if system is not None:
        options.setdefault("wrapping", system.wrapping())
        if kind != "pf" and system.disturbed is not None:
            options.setdefault("adapt_states", system.disturbed)
    if kind == "pf":  # a 12-D cloud collapses without regularised resampling, see _PF_DEFAULTS
        for key, value in _PF_DEFAULTS.items():
            options.setdefault(key, value)
    return cls(prediction, observation, **options)  # type: ignore[arg-type]


def build_filter(
    filter_kind: str, model_kind: str, model_dir: str | os.PathLike[str], **options: object
) -> EKF | UKF | PF:
    """``make_filter(filter_kind, *load_models(model_dir, model_kind), system=..., **options)``
    with the folder's system description and, for an EKF or UKF, its calibrated NIS/dof
    reference (:func:`adaptation_defaults`)."""
    models = load_models(model_dir, model_kind)
    if filter_kind != "pf":
        options = {**adaptation_defaults(model_dir, model_kind), **options}
    return make_filter(filter_kind, *models, system=read_system(model_dir), **options)


def adaptation_defaults(model_dir: str | os.PathLike[str], model_kind: str) -> dict[str, object]:
    """An adaptive EKF's or UKF's options from the model folder: ``adapt_reference``, the
    calibrated filter's NIS/dof level for ``model_kind`` where ``calibration.json`` has one
    (:mod:`estimator_service.filters.adaptive`)."""
    level = read_nis_reference(model_dir).get(model_kind)
    return {} if level is None else {"adapt_reference": level}


def warm_up(filt: EKF | UKF | PF, system: System) -> None:
    """One step from ``system``'s prior, so that the models compute their caches (e.g. the
    exact GP's inverse factors, about a second at paper size) now instead of on a user's
    first step."""
    rng = np.random.default_rng(0)
    prior = GaussianBelief(np.array(system.prior_mean), np.diag(np.square(system.prior_std)))
    m = system.obs_dim
    filt.step(filt.initial(prior, rng), np.zeros(system.control_dim), np.zeros(m), np.ones(m, bool), rng)
