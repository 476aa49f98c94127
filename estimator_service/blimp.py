"""The paper's micro-blimp as one :class:`~estimator_service.system.System`, and its
parametric model family (the rigid-body ODE of eq. 30 and the pinhole camera model).

Everything blimp-specific that the estimator needs lives here: the description
(:func:`blimp_system`), fitting the parametric models to flights (:func:`fit_parametric`),
and their file (:func:`save_parametric`, :func:`load_parametric`).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from estimator_service.files import atomic_savez
from estimator_service.models.blimp import BlimpODE, fit_blimp_ode
from estimator_service.models.camera import ELLIPSE_PERIODS, CameraModel, PinholeCalibration, fit_camera_model
from estimator_service.system import Group, Sensor, System

if TYPE_CHECKING:
    from estimator_service.flight import Flight

__all__ = [
    "BLIMP_STATE",
    "ELLIPSE_OUTPUTS",
    "blimp_system",
    "fit_parametric",
    "load_parametric",
    "measured",
    "save_parametric",
]

BLIMP_STATE = ("x", "y", "z", "roll", "pitch", "yaw", "u", "v", "w", "p", "q", "r")
BLIMP_CONTROLS = ("main_thrust", "vector_angle", "tail_thrust")
ELLIPSE_OUTPUTS = ("cx", "cy", "width", "height", "angle")
DEG, MM = 180.0 / math.pi, 1000.0
# paper units of Tables 5-9: mm, deg, mm/s, deg/s
BLIMP_GROUPS = (
    Group("position_mm", (0, 1, 2), MM),
    Group("orientation_deg", (3, 4, 5), DEG),
    Group("velocity_mm_s", (6, 7, 8), MM),
    Group("ang_velocity_deg_s", (9, 10, 11), DEG),
)
# the body velocities (u, v, w, p, q, r): gusts and a heavier or lighter blimp act on them;
# the position and angles are their integrals
BLIMP_DISTURBED = tuple(range(6, 12))
# a new session's prior: anywhere in the 10 x 6 x 4 m lab, any heading
PRIOR_MEAN = (5.0, 3.0, 2.0) + (0.0,) * 9
PRIOR_STD = (3.0, 2.0, 1.5, 0.3, 0.3, math.pi, 1.0, 1.0, 1.0, 0.5, 0.5, 0.5)


def blimp_system(n_cameras: int = 2, dt: float = 0.25, camera_rate_hz: float | None = 1.0) -> System:
    """The blimp: 12-D state (position m, Euler angles rad, body velocity m/s, body rates
    rad/s), 3 controls, ``n_cameras`` cameras each reporting an ellipse ``(cx, cy, w, h,
    angle)`` whose orientation has period pi. GPs see the yaw as ``(cos, sin)``."""
    cams = tuple(
        Sensor(f"cam{k}", ELLIPSE_OUTPUTS, ELLIPSE_PERIODS, camera_rate_hz) for k in range(n_cameras)
    )
    periods = (0.0,) * 3 + (2 * math.pi,) * 3 + (0.0,) * 6
    return System(
        "blimp", BLIMP_STATE, BLIMP_CONTROLS, cams, float(dt), periods, (5,), BLIMP_GROUPS,
        PRIOR_MEAN, PRIOR_STD, parametric="blimp", disturbed=BLIMP_DISTURBED,
    )  # fmt: skip


def calibrations(flight: Flight) -> tuple[PinholeCalibration, ...]:
    """The cameras' known calibration from a flight's metadata (distortion is ignored)."""
    cams = flight.metadata.get("cameras")
    if not cams:
        raise ValueError(
            "the blimp's parametric camera model needs the cameras' calibration in the flight's metadata"
        )
    return tuple(
        PinholeCalibration(
            np.array(c["position"]), np.array(c["rotation"]), float(c["focal"]),
            (float(c["principal_point"][0]), float(c["principal_point"][1])),
        )
        for c in cams
    )  # fmt: skip


def fit_parametric(
    flights: Sequence[Flight], x: np.ndarray, u: np.ndarray, x_next: np.ndarray
) -> tuple[BlimpODE, CameraModel]:
    """The ODE fitted to transitions ``x, u -> x_next`` and the camera model to every reading
    of ``flights``; the weighed mass and tail arm come from the first flight's metadata."""
    params = flights[0].metadata.get("params")
    if params is None:
        raise ValueError(
            "the blimp's parametric model needs 'params' (mass, tail_arm) in the flight's metadata"
        )
    ode = fit_blimp_ode(x, u, x_next, mass=params["mass"], tail_arm=params["tail_arm"], dt=flights[0].dt)
    state = np.concatenate([f.state for f in flights])
    z = np.concatenate([f.z for f in flights])
    valid = np.concatenate([f.valid for f in flights])
    return ode, fit_camera_model(calibrations(flights[0]), state, z, valid)


def measured(flights: Sequence[Flight], key: str) -> float:
    """A measured constant (``mass``, ``tail_arm``) of the blimp the flights flew: each
    episode's own value (``metadata["episode_params"]``, recorded under domain randomisation)
    weighted by its transitions, or ``metadata["params"]`` where episodes are not recorded."""
    values, weights = [], []
    for f in flights:
        per_episode = f.metadata.get("episode_params")
        if not per_episode and "params" not in f.metadata:
            raise ValueError(f"the blimp's parametric model needs '{key}' in the flights' metadata 'params'")
        counts = np.bincount(f.episode[f.transition_rows()], minlength=len(per_episode or ()))
        if per_episode and len(counts) == len(per_episode):
            values += [float(p[key]) for p in per_episode]
            weights += counts.tolist()
        else:  # episodes renumbered (e.g. cross-validation folds): the first episode's values
            values.append(float(f.metadata["params"][key]))
            weights.append(len(f.transition_rows()))
    if len(set(values)) == 1:
        return values[0]
    return float(np.average(values, weights=np.maximum(weights, 0) + 1e-12))


def save_parametric(ode: BlimpODE, cam: CameraModel, path: str | os.PathLike[str]) -> Path:
    """Write both parametric models to one ``.npz`` atomically."""
    arrays = {
        "ode_params": ode.params, "ode_noise": ode.noise_var,
        "ode_fixed": np.array([ode.mass, ode.tail_arm, ode.dt, ode.substeps]),
        "cam_position": np.stack([c.position for c in cam.cameras]),
        "cam_rotation": np.stack([c.rotation for c in cam.cameras]),
        "cam_focal": np.array([c.focal for c in cam.cameras]),
        "cam_principal": np.array([c.principal_point for c in cam.cameras]),
        "cam_axes": cam.semi_axes, "cam_noise": cam.noise_var,
    }  # fmt: skip
    return atomic_savez(path, **arrays)


def load_parametric(path: str | os.PathLike[str]) -> tuple[BlimpODE, CameraModel]:
    """Read the models written by :func:`save_parametric`."""
    with np.load(path, allow_pickle=False) as d:
        missing = {"ode_params", "ode_noise", "ode_fixed", "cam_axes", "cam_noise"} - set(d.files)
        if missing:
            raise ValueError(f"parametric model file {os.fspath(path)!r} lacks {sorted(missing)}")
        mass, tail, dt, sub = d["ode_fixed"]
        ode = BlimpODE(d["ode_params"], d["ode_noise"], float(mass), float(tail), float(dt), int(sub))
        cams = tuple(
            PinholeCalibration(p, r, float(f), (float(c[0]), float(c[1])))
            for p, r, f, c in zip(
                d["cam_position"], d["cam_rotation"], d["cam_focal"], d["cam_principal"], strict=True
            )
        )
        return ode, CameraModel(cams, d["cam_axes"], d["cam_noise"])
