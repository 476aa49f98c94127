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
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from estimator_service.filters import EKF, PF, UKF, GaussianBelief
from estimator_service.filters.adaptive import ADAPT_RATE
from estimator_service.gp import load_gp
from estimator_service.models.base import ObservationModel, PredictionModel
from estimator_service.models.calibration import (
    NoiseScaledObservation,
    NoiseScaledPrediction,
    read_adaptive,
    read_nis_reference,
    read_noise_scales,
    read_observation_scales,
    read_process_ceiling,
    read_process_scales,
)
from estimator_service.models.gp_models import (
    GPObservationModel,
    GPPredictionModel,
    SharedGPObservation,
    StackedObservationModel,
)
from estimator_service.store import check_folder, read_system
from estimator_service.system import System
from estimator_service.user_models import USER_MODELS_FILE, UserSensorModel, load_user_models, user_models

__all__ = [
    "FILTER_KINDS",
    "MODEL_KINDS",
    "Parametric",
    "adaptation_defaults",
    "apply_calibration",
    "build_filter",
    "folder_kinds",
    "load_models",
    "load_parametric",
    "make_filter",
    "noise_floors",
    "observation_files",
    "observation_parts",
    "warm_up",
]

FILTER_KINDS = ("ukf", "ekf", "pf")
MODEL_KINDS = ("param", "gp", "egp", "hetgp", "sparse")
#: kinds whose GPs model the residual of the parametric models (paper eq. 16); the
#: heteroscedastic GP is one of them, as the paper's Tables 7-8 rank it above the EGP.
ENHANCED_KINDS = ("egp", "hetgp")
PARAMETRIC_FILE = "parametric.npz"
#: the kind a command runs when none is named: the first the folder has, in the paper's
#: ranking of the models (Tables 7-8: hetGP, then EGP, GP, the sparse GP, parametric last)
MODEL_PREFERENCE = ("hetgp", "egp", "gp", "sparse", "param")


@dataclass(frozen=True)
class Parametric:
    """A system's parametric models as the factory uses them: the filters' models, the
    prediction's mean change (the enhanced kinds' prediction mean) and, per sensor, the
    mean function of its observation GP's inputs (the state, then its type's constants)."""

    prediction: PredictionModel
    observation: ObservationModel
    change: Callable[[np.ndarray, np.ndarray], np.ndarray]
    sensor_means: dict[str, Callable[[np.ndarray], np.ndarray]]
    sensor_jacobians: dict[str, Callable[[np.ndarray], np.ndarray]] = field(default_factory=dict)


def load_parametric(folder: str | os.PathLike[str], system: System) -> Parametric:
    """The system's parametric models: the blimp's ODE and camera model, or the user's
    fitted models (:mod:`estimator_service.user_models`)."""
    folder = Path(folder)
    if not system.has_parametric:
        raise ValueError(
            f"system {system.name!r} has no parametric models: the 'param', 'egp' and 'hetgp' "
            "kinds need a 'prediction_model' and a model for every sensor's type; use 'gp' or 'sparse'"
        )
    if system.parametric == "blimp":
        from estimator_service.blimp import load_parametric as load_blimp

        ode, cam = load_blimp(folder / PARAMETRIC_FILE)
        means = {
            part: partial(_columns_of, cam.mean, _columns(system, ks))
            for part, ks in observation_parts(system).items()
        }
        return Parametric(ode, cam, ode.change, means)
    pred, types = user_models(load_user_models(folder / USER_MODELS_FILE, system), system)
    n, parts = system.state_dim, {_type_part(t): m for t, m in types.items()}
    means = {part: partial(_readings_at, m, n) for part, m in parts.items()}
    jacobians = {part: partial(_state_jacobian, m, n) for part, m in parts.items()}
    columns = [_columns(system, observation_parts(system)[part]) for part in parts]
    stacked = StackedObservationModel(tuple(parts.values()), tuple(columns))
    return Parametric(pred, stacked, pred.change, means, jacobians)


def _readings_at(model: UserSensorModel, n: int, q: np.ndarray) -> np.ndarray:
    """A type's readings at its GP's inputs ``q = [x, c]`` ``(M, n + c)``."""
    return model.readings(q[:, :n], q[:, n:])


def _state_jacobian(model: UserSensorModel, n: int, q: np.ndarray) -> np.ndarray:
    """``d h / d [x, c]`` ``(M, size, n + c)`` of a type's model at ``q = [x, c]``: the state
    block (angle outputs' differences wrapped, or the user's Jacobian), zeros for the
    constants (the filters use the state block only)."""
    jac = model.readings_and_jacobian(q[:, :n], q[:, n:])[1]
    return np.concatenate([jac, np.zeros((*jac.shape[:2], q.shape[1] - n))], axis=2)


def _columns_of(f: Callable[[np.ndarray], np.ndarray], cols: np.ndarray, x: np.ndarray) -> np.ndarray:
    return f(x)[:, cols]


def _columns(system: System, sensors: tuple[int, ...]) -> np.ndarray:
    """The observation columns of ``sensors``, sensor by sensor."""
    return np.concatenate(
        [np.arange(system.sensor_slice(k).start, system.sensor_slice(k).stop) for k in sensors]
    )


def _type_part(type_name: str) -> str:
    return f"type-{type_name}"


def observation_parts(system: System) -> dict[str, tuple[int, ...]]:
    """The observation models' parts and the sensors each covers: ``cam<k>`` for each sensor
    without a type (its own model), ``type-<name>`` for each sensor type (one model its
    sensors share, with their constants as inputs). The one owner of the part names."""
    parts = {f"cam{k}": (k,) for k, s in enumerate(system.sensors) if s.type is None}
    parts.update({_type_part(t): ks for t, ks in system.sensors_of_type().items()})
    return parts


def observation_files(system: System, kind: str) -> dict[str, str]:
    """``{part: file name}`` of a GP kind's observation models (:func:`observation_parts`)."""
    return {part: f"observation_{kind}_{part}.npz" for part in observation_parts(system)}


def folder_kinds(folder: str | os.PathLike[str], system: System) -> list[str]:
    """The model kinds a trained folder holds, in :data:`MODEL_KINDS` order: ``param`` where
    it has the parametric models, a GP kind where it has its prediction model (and, for the
    enhanced kinds, the parametric models they refine)."""
    folder = Path(folder)
    param = (folder / (PARAMETRIC_FILE if system.parametric == "blimp" else USER_MODELS_FILE)).exists()
    param = param and system.has_parametric
    held = {k for k in MODEL_KINDS if k != "param" and (folder / f"prediction_{k}.npz").exists()}
    return [
        k
        for k in MODEL_KINDS
        if (k == "param" and param) or (k in held and (param or k not in ENHANCED_KINDS))
    ]


def preferred_kind(folder: str | os.PathLike[str]) -> str:
    """The kind a command runs on ``folder`` when none is named (:data:`MODEL_PREFERENCE`)."""
    have = folder_kinds(folder, read_system(Path(folder)))
    if not have:
        raise ValueError(f"model folder {os.fspath(folder)} holds no trained models: run 'gpbf train'")
    return next(k for k in MODEL_PREFERENCE if k in have)


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
        check_folder(folder, hashes=True)  # a same-size edit of a model file is refused too
    system = read_system(folder)
    if kind not in (present := folder_kinds(folder, system)):
        have = ", ".join(present) or "none"
        raise ValueError(
            f"model folder {folder} has no {kind!r} models (it has: {have}); choose one with --model"
        )
    n = system.state_dim
    param = load_parametric(folder, system) if kind == "param" or kind in ENHANCED_KINDS else None
    if param is not None and kind == "param":
        pred, obs = param.prediction, param.observation
    else:
        extra_p = {}
        if param is not None:
            change = param.change
            extra_p = {"mean_function": lambda q: change(q[:, :n], q[:, n:])}
        pred = GPPredictionModel(load_gp(folder / f"prediction_{kind}.npz", **extra_p), n)
        obs = _observation(folder, kind, system, param)
    return apply_calibration(folder, kind, pred, obs, system=system) if calibrated else (pred, obs)


def apply_calibration(
    folder: str | os.PathLike[str], kind: str, pred: PredictionModel, obs: ObservationModel,
    *, process: bool = True, scales: bool = True, system: System | None = None,
) -> tuple[PredictionModel, ObservationModel]:  # fmt: skip
    """``pred`` and ``obs`` with the noise scales of ``folder/calibration.json`` for ``kind``
    (where there are any; none with ``scales=False``), the process-variance ceiling (where
    there is one) and the system's noise floors (where it declares any; ``system`` defaults
    to the folder's); ``process=False`` leaves the prediction noise as it is."""
    system = read_system(folder) if system is None else system
    scale = read_noise_scales(folder).get(kind, 1.0) if process and scales else 1.0
    if process and scales and kind in (per_output := read_process_scales(folder)):
        scale = scale * per_output[kind]
    ceiling = read_process_ceiling(folder, pred.state_dim) if process else None
    p_floor, o_floor = noise_floors(system)
    p_floor = p_floor if process else None
    obs_scale = read_observation_scales(folder).get(kind) if scales else None
    plain = ceiling is None and p_floor is None and np.all(np.asarray(scale) == 1.0)
    if obs_scale is not None or o_floor is not None:
        obs = NoiseScaledObservation(obs, np.ones(obs.obs_dim) if obs_scale is None else obs_scale, o_floor)
    return (pred if plain else NoiseScaledPrediction(pred, scale, ceiling, p_floor), obs)


def noise_floors(system: System) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The system's process (``(n,)``) and observation (``(m,)``) noise floors as variances,
    None where it declares none."""
    proc = np.square(system.process_noise_floor)
    obs = np.square([f for s in system.sensors for f in s.noise_floor])
    return (proc if proc.any() else None), (obs if obs.any() else None)


def _observation(folder: Path, kind: str, system: System, param: Parametric | None) -> ObservationModel:
    """One file for all sensors, or one file per sensor without a type and one per sensor
    type (:func:`observation_files`); the parametric sensor means (``param``) are the
    enhanced kinds' mean functions."""
    single = folder / f"observation_{kind}.npz"
    if single.exists():
        extra = {} if param is None else {"mean_function": lambda x: param.observation.observe(x).mean}
        return GPObservationModel(load_gp(single, **extra))
    parts, columns = [], []
    files = observation_files(system, kind)
    for part, ks in observation_parts(system).items():
        extra = {}
        if param is not None:
            extra = {
                "mean_function": param.sensor_means[part],
                "mean_jacobian": param.sensor_jacobians.get(part),
            }
        gp = load_gp(folder / files[part], **extra)
        if system.sensors[ks[0]].type is None:
            parts.append(GPObservationModel(gp))
        else:
            consts = np.array([system.sensors[k].constants for k in ks], dtype=np.float64)
            parts.append(SharedGPObservation(gp, consts.reshape(len(ks), -1)))
        columns.append(_columns(system, ks))
    in_order = all(s.type is None for s in system.sensors)
    return StackedObservationModel(tuple(parts), None if in_order else tuple(columns))


# Regularised resampling with the Kalman-updated covariance of the predicted cloud; measured:
# docs/measurements.md#pf-roughening-kernel
_PF_DEFAULTS: dict[str, object] = {"roughen": 1.0, "roughen_cov": "kalman"}
#: the PF's update for each model kind where the caller names none: the bridged update for
#: the learned models, whose sharp observation GPs collapse Table 1's weights (the GP-PFs lost
#: whole test segments); Table 1's for the parametric models, where the bridge raised the RMS.
#: Chosen by a rule fixed before its runs: docs/measurements.md#pf-bridged-update
PF_UPDATE_RULES: dict[str, str] = {k: "table1" if k == "param" else "bridge" for k in MODEL_KINDS}


def make_filter(
    kind: str, prediction: PredictionModel, observation: ObservationModel, *,
    system: System | None = None, model_kind: str | None = None, **options: object,
) -> EKF | UKF | PF:  # fmt: skip
    """A filter of ``kind`` (``ekf``, ``ukf``, ``pf``) over the given models.

    ``system`` sets the angle handling (``wrapping``) and which states an adaptive filter
    inflates (``adapt_states``, its ``disturbed`` components); ``model_kind`` (one of
    :data:`MODEL_KINDS`, None: models of no kind) sets the PF's ``update_rule``
    (:data:`PF_UPDATE_RULES`; Table 1's for None); ``options`` go to the filter
    (e.g. ``alpha`` for the UKF, ``n_particles`` for the PF). An EKF or UKF adapts its
    process noise at :data:`~estimator_service.filters.adaptive.ADAPT_RATE` unless
    ``adapt_rate`` says otherwise (0: the paper's filter).
    """
    if kind not in FILTER_KINDS:
        raise ValueError(f"filter kind must be one of {FILTER_KINDS}, got {kind!r}")
    if model_kind is not None and model_kind not in MODEL_KINDS:
        raise ValueError(f"model_kind must be one of {MODEL_KINDS} or None, got {model_kind!r}")
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
        options.setdefault("update_rule", PF_UPDATE_RULES[model_kind or "param"])
    return cls(prediction, observation, **options)  # type: ignore[arg-type]


def build_filter(
    filter_kind: str, model_kind: str, model_dir: str | os.PathLike[str], *, calibrated: bool = True,
    **options: object,
) -> EKF | UKF | PF:  # fmt: skip
    """``make_filter(filter_kind, *load_models(model_dir, model_kind), system=..., **options)``
    with the folder's system description and, for an EKF or UKF, its calibrated NIS/dof
    reference (:func:`adaptation_defaults`).

    ``calibrated=False``: the same models without the calibration's noise scales (the
    process-variance ceiling and the system's noise floors kept, as for every filter) and,
    for an EKF or UKF, without adaptation (it has no calibrated reference): what the
    calibration is judged against."""
    if calibrated:
        models, adapt = load_models(model_dir, model_kind), adaptation_defaults(model_dir, model_kind)
    else:
        raw = load_models(model_dir, model_kind, calibrated=False)
        models, adapt = apply_calibration(model_dir, model_kind, *raw, scales=False), {"adapt_rate": 0.0}
    if filter_kind != "pf":
        options = {**adapt, **options}
    return make_filter(filter_kind, *models, system=read_system(model_dir), model_kind=model_kind, **options)


def adaptation_defaults(model_dir: str | os.PathLike[str], model_kind: str) -> dict[str, object]:
    """An adaptive EKF's or UKF's options from the model folder: ``adapt_reference``, the
    calibrated filter's NIS/dof level for ``model_kind`` where ``calibration.json`` has one
    (:mod:`estimator_service.filters.adaptive`), and ``adapt_rate`` 0 where the cross-fitted
    calibration found the plain filter better on its held-out blocks."""
    level = read_nis_reference(model_dir).get(model_kind)
    options: dict[str, object] = {} if level is None else {"adapt_reference": level}
    if read_adaptive(model_dir).get(model_kind) is False:
        options["adapt_rate"] = 0.0
    return options


def warm_up(filt: EKF | UKF | PF, system: System) -> None:
    """One step from ``system``'s prior, so that the models compute their caches (e.g. the
    exact GP's inverse factors, about a second at paper size) now instead of on a user's
    first step."""
    rng = np.random.default_rng(0)
    prior = GaussianBelief(np.array(system.prior_mean), np.diag(np.square(system.prior_std)))
    m = system.obs_dim
    filt.step(filt.initial(prior, rng), np.zeros(system.control_dim), np.zeros(m), np.ones(m, bool), rng)
