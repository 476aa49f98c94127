"""Parametric camera observation model (paper Sect. 6.1.2).

The blimp pose is taken into each camera's frame, the envelope's three axes are projected
through an undistorted pinhole with known calibration, and the image ellipse follows
geometrically from the projected half-axes ``h_i``: centre at the projected centre, shape
``S = sum_i h_i h_i^T``. It ignores the lens' barrel distortion, as the paper's did. The
envelope semi-axes (2 parameters) are fitted by least squares; the noise variance is the
mean squared residual. Observation per camera: ``(cx, cy, width, height, angle)`` with the
angle of period pi; all cameras are stacked into one vector ``(5 C,)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from estimator_service.angles import wrap_angle
from estimator_service.models.base import ModelOutput
from estimator_service.models.rotation import euler_matrix
from estimator_service.reprs import short_repr

__all__ = ["ELLIPSE_PERIODS", "CameraModel", "PinholeCalibration", "ellipse_from_shape", "fit_camera_model"]

FloatArray = NDArray[np.float64]

#: periods of an ellipse reading (cx, cy, width, height, orientation): the orientation has period pi
ELLIPSE_PERIODS = (0.0, 0.0, 0.0, 0.0, math.pi)


@dataclass(frozen=True)
class PinholeCalibration:
    """Known calibration of one camera.

    Attributes
    ----------
    position: (3,)
        Optical centre in the world (m).
    rotation: (3, 3)
        World-to-camera rotation (rows: camera x right, y down, z forward).
    focal
        Focal length (px).
    principal_point
        ``(cx, cy)`` (px).
    """

    position: FloatArray
    rotation: FloatArray
    focal: float
    principal_point: tuple[float, float]

    def project(self, points: FloatArray) -> FloatArray:
        """World points ``(..., 3)`` to undistorted pixels ``(..., 2)``."""
        pc = (points - self.position) @ self.rotation.T
        return self.focal * pc[..., :2] / pc[..., 2:3] + np.asarray(self.principal_point)


def ellipse_from_shape(centre: FloatArray, shape: FloatArray) -> FloatArray:
    """Ellipse ``(..., 5)`` from centre ``(..., 2)`` and shape ``S (..., 2, 2)``."""
    a, b, c = shape[..., 0, 0], shape[..., 0, 1], shape[..., 1, 1]
    half, rad = 0.5 * (a + c), np.sqrt(0.25 * (a - c) ** 2 + b * b)
    angle = wrap_angle(0.5 * np.arctan2(2 * b, a - c), math.pi)
    w, h = 2 * np.sqrt(half + rad), 2 * np.sqrt(np.maximum(half - rad, 0.0))
    return np.stack([centre[..., 0], centre[..., 1], w, h, angle], axis=-1)


def project_ellipses(
    cams: tuple[PinholeCalibration, ...], x: FloatArray, semi_axes: FloatArray
) -> FloatArray:
    """Ellipses ``(M, 5 C)`` of states ``x (M, >= 6)`` for envelope semi-axes ``(a, b)``."""
    pos, rot = x[:, :3], euler_matrix(x[:, 3:6])
    scales = np.array([semi_axes[0], semi_axes[1], semi_axes[1]])
    tips = rot * scales[None, None, :]  # columns: body axes in the world, scaled
    out = []
    for cam in cams:  # a handful of cameras; vectorised over rows
        plus = cam.project(pos[:, None, :] + tips.transpose(0, 2, 1))
        minus = cam.project(pos[:, None, :] - tips.transpose(0, 2, 1))
        half = 0.5 * (plus - minus)  # (M, 3, 2)
        shape = np.einsum("mki,mkj->mij", half, half)
        out.append(ellipse_from_shape(cam.project(pos), shape))
    return np.concatenate(out, axis=1)


@dataclass(frozen=True)
class CameraModel:
    """Fitted parametric observation model for ``C`` cameras (:class:`ObservationModel`).

    Attributes
    ----------
    cameras
        Known calibrations.
    semi_axes: (2,)
        Fitted envelope semi-axes ``(a, b)`` (m).
    noise_var: (5 C,)
    """

    __repr__ = short_repr

    cameras: tuple[PinholeCalibration, ...]
    semi_axes: FloatArray
    noise_var: FloatArray
    state_dim: int = 12

    @property
    def obs_dim(self) -> int:
        return 5 * len(self.cameras)

    @property
    def obs_periods(self) -> FloatArray:
        """Period of each observation value: pi for ellipse angles, else 0."""
        return np.tile(ELLIPSE_PERIODS, len(self.cameras))

    def mean(self, x: FloatArray) -> FloatArray:
        return project_ellipses(self.cameras, x, self.semi_axes)

    def observe(self, x: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        mean = self.mean(x)
        j = self._jacobian(x) if jac else None
        return ModelOutput(mean, np.broadcast_to(self.noise_var, mean.shape), j)

    def _jacobian(self, x: FloatArray, step: float = 1e-6) -> FloatArray:
        """Central differences ``(M, 5 C, n)`` in one batched call; angle differences wrapped."""
        m, n = x.shape
        pts = np.concatenate([x[:, None, :] + step * np.eye(n), x[:, None, :] - step * np.eye(n)], axis=1)
        f = self.mean(pts.reshape(-1, n)).reshape(m, 2, n, -1)
        d = f[:, 0] - f[:, 1]
        return (wrap_angle(d, self.obs_periods) / (2 * step)).transpose(0, 2, 1)


def fit_camera_model(
    cameras: tuple[PinholeCalibration, ...],
    x: FloatArray,
    z: FloatArray,
    valid: NDArray[np.bool_],
    initial_axes: tuple[float, float] = (0.8, 0.3),
) -> CameraModel:
    """Fit the semi-axes to states ``x (N, 12)``, ellipses ``z (N, 5 C)`` and ``valid (N, C)``."""
    x, z = np.asarray(x, dtype=np.float64), np.asarray(z, dtype=np.float64)
    mask = np.repeat(np.asarray(valid, dtype=bool), 5, axis=1)
    if x.shape[0] != z.shape[0] or z.shape[1] != 5 * len(cameras) or mask.shape != z.shape:
        raise ValueError(f"need x (N, 12), z (N, {5 * len(cameras)}), valid (N, {len(cameras)})")
    if not mask.any():
        raise ValueError("no valid camera frames to fit the camera model to")
    periods = np.tile(ELLIPSE_PERIODS, len(cameras))

    def resid(ab: FloatArray) -> FloatArray:
        r = project_ellipses(cameras, x, np.exp(ab)) - z
        r = wrap_angle(r, periods)
        return np.where(mask, r, 0.0).ravel()

    res = least_squares(resid, np.log(initial_axes), method="trf")
    r = resid(res.x).reshape(z.shape)
    var = (r * r).sum(axis=0) / np.maximum(mask.sum(axis=0), 1) + 1e-9
    return CameraModel(tuple(cameras), np.exp(res.x), var)
