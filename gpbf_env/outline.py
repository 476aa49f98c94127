"""Compiled kernels of the cameras: the closed-form mode
(:func:`gpbf_env.camera.outline_ellipses`) and the moment ellipse fit.

Per blimp and camera: the outline conic of the envelope ``C* = K M K^T`` (see
:mod:`gpbf_env.camera`), its ellipse sampled at the unit circle's points, barrel
distortion, pixel noise, and the second-moment fit. Scalar code compiled by numba, one
blimp and camera at a time, with the array code's operations.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from gpbf_env.jit import kernel

__all__ = ["CAMERA_COLUMNS", "fit_points", "outline_kernel"]

#: the columns of a camera's row in the kernel's camera table (pixels; k1, k2 radial terms)
CAMERA_COLUMNS = ("focal", "cx", "cy", "k1", "k2", "width", "height")
FOCAL, CX, CY, K1, K2, WIDTH, HEIGHT = range(len(CAMERA_COLUMNS))

FloatArray = NDArray[np.float64]
_HALF_PI = math.pi / 2


@kernel
def _ellipse(cx: float, cy: float, a: float, b: float, c: float) -> tuple[float, float, float, float, float]:
    """``(cx, cy, width, height, angle)`` of the ellipse with shape ``[[a, b], [b, c]]``."""
    half, diff = 0.5 * (a + c), 0.5 * (a - c)
    rad = np.sqrt(diff * diff + b * b)
    lam1 = half + rad
    lam2 = max(half - rad, 0.0)
    angle = 0.5 * math.atan2(2.0 * b, a - c)
    if angle <= -_HALF_PI:
        angle = angle + math.pi
    return cx, cy, 2 * np.sqrt(lam1), 2 * np.sqrt(lam2), angle


@kernel
def _moment_fit(pts: FloatArray, factor: float) -> tuple[float, float, float, float, float]:
    """Ellipse of points ``pts`` (K, 2): centre = mean, shape = ``factor`` x covariance."""
    n_pts = pts.shape[0]
    mx, my = pts[:, 0].mean(), pts[:, 1].mean()
    sxx = sxy = syy = 0.0
    for i in range(n_pts):
        dx, dy = pts[i, 0] - mx, pts[i, 1] - my
        sxx += dx * dx
        sxy += dx * dy
        syy += dy * dy
    return _ellipse(mx, my, factor * (sxx / n_pts), factor * (sxy / n_pts), factor * (syy / n_pts))


@kernel
def fit_points(points: FloatArray, factor: float, out: FloatArray) -> None:
    """Moment-fit ellipses ``out`` (M, 5) of point sets ``points`` (M, K, 2)."""
    for m in range(points.shape[0]):
        fit = _moment_fit(points[m], factor)
        for j in range(5):
            out[m, j] = fit[j]


@kernel
def _conic(
    rot: FloatArray, pos: FloatArray, cam_rot: FloatArray, cam_pos: FloatArray, axes2: FloatArray
) -> tuple[FloatArray, float]:
    """``M = R A R^T - c c^T`` (3, 3) in camera coordinates, and the depth of the centre ``c``."""
    rc, cc, m = np.empty((3, 3)), np.empty(3), np.empty((3, 3))
    for i in range(3):
        cc[i] = 0.0
        for j in range(3):
            cc[i] += (pos[j] - cam_pos[j]) * cam_rot[i, j]
            rc[i, j] = cam_rot[i, 0] * rot[0, j] + cam_rot[i, 1] * rot[1, j] + cam_rot[i, 2] * rot[2, j]
    for i in range(3):
        for j in range(3):
            m[i, j] = rc[i, 0] * axes2[0] * rc[j, 0] + rc[i, 1] * axes2[1] * rc[j, 1]
            m[i, j] += rc[i, 2] * axes2[2] * rc[j, 2]
            m[i, j] -= cc[i] * cc[j]
    return m, cc[2]


@kernel
def _project(m: FloatArray, f: float, px: float, py: float) -> FloatArray:
    """``K m K^T`` for the pinhole ``K = [[f, 0, px], [0, f, py], [0, 0, 1]]``."""
    km = np.empty((3, 3))
    for j in range(3):
        km[0, j] = f * m[0, j] + px * m[2, j]
        km[1, j] = f * m[1, j] + py * m[2, j]
        km[2, j] = m[2, j]
    out = np.empty((3, 3))
    for i in range(3):
        out[i, 0] = km[i, 0] * f + km[i, 2] * px
        out[i, 1] = km[i, 1] * f + km[i, 2] * py
        out[i, 2] = km[i, 2]
    return out


@kernel
def _sample(
    ellipse: tuple[float, float, float, float, float], cam: FloatArray, circle: FloatArray,
    noise: FloatArray, pts: FloatArray,
) -> None:  # fmt: skip
    """Distorted, noisy pixels ``pts`` (K, 2) of an ideal ``ellipse`` at the ``circle``'s angles.

    ``cam`` is ``(focal, cx, cy, k1, k2, ...)``, ``noise`` (K, 2) pixel noise.
    """
    ex, ey, wd, ht, ang = ellipse
    f, px, py, k1, k2 = cam[FOCAL], cam[CX], cam[CY], cam[K1], cam[K2]
    a1, a2 = 0.5 * wd, 0.5 * ht
    c1, s1 = math.cos(ang), math.sin(ang)
    for i in range(pts.shape[0]):
        u, v = a1 * circle[i, 0], a2 * circle[i, 1]
        xn, yn = (ex + u * c1 - v * s1 - px) / f, (ey + u * s1 + v * c1 - py) / f
        r2 = xn * xn + yn * yn
        scale = 1.0 + k1 * r2 + k2 * r2 * r2
        pts[i, 0] = xn * scale * f + px + noise[i, 0]
        pts[i, 1] = yn * scale * f + py + noise[i, 1]


@kernel
def outline_kernel(
    position: FloatArray, rotation: FloatArray, axes2: FloatArray, cam_rot: FloatArray, cam_pos: FloatArray,
    cam_k: FloatArray, circle: FloatArray, noise: FloatArray, out: FloatArray, visible: NDArray[np.bool_],
) -> None:  # fmt: skip
    """Fill ``out`` (N, C, 5) and ``visible`` (N, C) for ``N`` blimps and ``C`` cameras.

    ``position`` (N, 3), ``rotation`` (N, 3, 3), ``axes2`` (3,) squared semi-axes;
    ``cam_rot`` (C, 3, 3), ``cam_pos`` (C, 3), ``cam_k`` (C, 7) rows of
    :data:`CAMERA_COLUMNS` with ``(cx, cy)`` the principal point;
    ``circle`` (K, 2) unit-circle samples; ``noise`` (N, C, K, 2) pixel noise.
    """
    n_pts = circle.shape[0]
    pts = np.empty((n_pts, 2))
    for n in range(position.shape[0]):
        for k in range(cam_rot.shape[0]):
            f, px, py = cam_k[k, FOCAL], cam_k[k, CX], cam_k[k, CY]
            width, height = cam_k[k, WIDTH], cam_k[k, HEIGHT]
            m, depth = _conic(rotation[n], position[n], cam_rot[k], cam_pos[k], axes2)
            cstar = _project(m, f, px, py)
            denom = -cstar[2, 2]
            ok = denom > 1e-9 and depth > 0
            if not ok:
                denom = 1.0
            ex, ey = -cstar[0, 2] / denom, -cstar[1, 2] / denom
            sa = cstar[0, 0] / denom + ex * ex
            sb = cstar[0, 1] / denom + ex * ey
            sc = cstar[1, 1] / denom + ey * ey
            _sample(_ellipse(ex, ey, sa, sb, sc), cam_k[k], circle, noise[n, k], pts)
            fit = _moment_fit(pts, 2.0)
            inside = 0 <= fit[0] <= width - 1 and 0 <= fit[1] <= height - 1
            visible[n, k] = ok and inside and fit[2] < 2 * width
            for j in range(5):
                out[n, k, j] = fit[j] if visible[n, k] else 0.0
