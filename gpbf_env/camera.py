"""Wall-mounted pinhole cameras with barrel distortion that report image ellipses.

Two ways of seeing the envelope (an ellipsoid):

* closed form (fast): the outline of a quadric under a pinhole camera is the conic whose
  dual is ``C* = K M K^T`` with ``M = R A R^T - c c^T`` in camera coordinates (``A`` the
  squared semi-axes, ``R`` the envelope attitude, ``c`` its centre). We sample the conic
  at ``K`` equally spaced parameter angles, apply the radial distortion and pixel noise,
  and fit an ellipse by second moments (for equally spaced points on an ellipse the
  moment fit is exact: centre = mean, shape = 2 x covariance).
* rendered (slow, like the paper's cameras; :mod:`gpbf_env.imaging`): every pixel's
  distorted ray is tested against the ellipsoid, the silhouette is painted into a noisy
  image over a static background, and the ellipse is fitted to the background-subtracted
  foreground (shape = 4 x covariance of a filled ellipse's pixels).

An ellipse is ``(cx, cy, width, height, angle)`` in pixels: centre, full major and minor
axis lengths, and the major axis angle from the image x axis (towards image y, which
points down), wrapped to ``(-pi/2, pi/2]`` because an ellipse rotated by pi is itself.
Camera frame: x right, y down, z along the optical axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from gpbf_env.outline import CAMERA_COLUMNS, fit_points, outline_kernel

__all__ = ["Camera", "default_cameras", "ellipse_from_points", "euler_to_matrix", "outline_ellipses"]

FloatArray = NDArray[np.float64]
N_BOUNDARY = 16  # conic samples per outline in the closed-form mode


def euler_to_matrix(euler: FloatArray) -> FloatArray:
    """Body-to-world rotation ``Rz(psi) Ry(theta) Rx(phi)``.

    Parameters
    ----------
    euler: (N, 3)
        Roll, pitch, yaw (rad).

    Returns
    -------
    R: (N, 3, 3)
    """
    sf, st, sp = np.sin(euler).T
    cf, ct, cp = np.cos(euler).T
    rows = (
        cp * ct, cp * st * sf - sp * cf, cp * st * cf + sp * sf,
        sp * ct, sp * st * sf + cp * cf, sp * st * cf - cp * sf,
        -st, ct * sf, ct * cf,
    )  # fmt: skip
    return np.stack(rows, axis=-1).reshape(-1, 3, 3)


@dataclass(frozen=True)
class Camera:
    """A calibrated pinhole camera with two-term radial distortion.

    Attributes
    ----------
    position: (3,)
        Optical centre in the world (m).
    rotation: (3, 3)
        World-to-camera rotation; its rows are the camera x, y, z axes in the world.
    focal
        Focal length (pixels), equal in x and y.
    size
        Image ``(width, height)`` in pixels.
    k1, k2
        Radial distortion ``x_d = x (1 + k1 r^2 + k2 r^4)`` in normalised coordinates;
        ``k1 < 0`` is barrel distortion.
    rate_hz, phase_s
        Frame rate and the time of the first frame; frames are staggered between cameras.
    """

    position: FloatArray
    rotation: FloatArray
    focal: float = 380.0
    size: tuple[int, int] = (640, 480)
    k1: float = -0.10
    k2: float = 0.01
    rate_hz: float = 1.0
    phase_s: float = 0.0
    name: str = field(default="cam")

    @classmethod
    def look_at(cls, position: FloatArray, target: FloatArray, **kwargs: object) -> Camera:
        """A camera at ``position`` whose optical axis points at ``target`` (world z is up)."""
        pos = np.asarray(position, dtype=np.float64)
        fwd = np.asarray(target, dtype=np.float64) - pos
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        return cls(position=pos, rotation=np.stack([right, down, fwd]), **kwargs)  # type: ignore[arg-type]

    @property
    def principal_point(self) -> tuple[float, float]:
        """Image centre ``(cx, cy)`` in pixels."""
        return (self.size[0] - 1) / 2.0, (self.size[1] - 1) / 2.0

    def intrinsics(self) -> FloatArray:
        """The 3x3 calibration matrix ``K``."""
        cx, cy = self.principal_point
        return np.array([[self.focal, 0.0, cx], [0.0, self.focal, cy], [0.0, 0.0, 1.0]])

    def project(self, points: FloatArray, distort: bool = True) -> tuple[FloatArray, FloatArray]:
        """Project world points to pixels.

        Parameters
        ----------
        points: (..., 3)

        Returns
        -------
        pixels: (..., 2)
        depth: (...)
            Distance along the optical axis; ``<= 0`` is behind the camera.
        """
        pc = (np.asarray(points, dtype=np.float64) - self.position) @ self.rotation.T
        depth = pc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = pc[..., :2] / depth[..., None]
        if distort:
            xn = self.distort_normalized(xn)
        cx, cy = self.principal_point
        return xn * self.focal + np.array([cx, cy]), depth

    def distort_normalized(self, xn: FloatArray) -> FloatArray:
        """Apply the radial distortion to normalised coordinates ``(..., 2)``."""
        r2 = np.sum(xn * xn, axis=-1, keepdims=True)
        return xn * (1.0 + self.k1 * r2 + self.k2 * r2 * r2)

    def distort_pixels(self, pix: FloatArray) -> FloatArray:
        """Map ideal (undistorted) pixels ``(..., 2)`` to distorted pixels."""
        pp = np.array(self.principal_point)
        return self.distort_normalized((pix - pp) / self.focal) * self.focal + pp

    @cached_property
    def pixel_rays(self) -> FloatArray:
        """Undistorted camera-frame ray directions of every pixel centre, ``(H*W, 3)``."""
        w, h = self.size
        uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        cx, cy = self.principal_point
        xd = np.stack([(uu.ravel() - cx) / self.focal, (vv.ravel() - cy) / self.focal], axis=-1)
        xu = xd.copy()
        for _ in range(20):  # fixed-point inversion of the radial model
            r2 = np.sum(xu * xu, axis=-1, keepdims=True)
            xu = xd / (1.0 + self.k1 * r2 + self.k2 * r2 * r2)
        return np.concatenate([xu, np.ones((xu.shape[0], 1))], axis=-1)


def default_cameras(
    room: tuple[float, float, float], rate_hz: float = 1.0, n_cameras: int = 2
) -> tuple[Camera, ...]:
    """Cameras high in opposite corners of the room looking at its centre, frames staggered."""
    lx, ly, lz = room
    target = np.array([lx / 2, ly / 2, lz * 0.4])
    corners = [(0.05, 0.05), (lx - 0.05, ly - 0.05), (lx - 0.05, 0.05), (0.05, ly - 0.05)]
    if not 1 <= n_cameras <= len(corners):
        raise ValueError(f"n_cameras must be in 1..{len(corners)}, got {n_cameras}")
    period = 1.0 / rate_hz
    return tuple(
        Camera.look_at(
            np.array([cx, cy, lz - 0.1]),
            target,
            rate_hz=rate_hz,
            phase_s=period * k / n_cameras,
            name=f"cam{k}",
        )
        for k, (cx, cy) in enumerate(corners[:n_cameras])
    )


def ellipse_from_points(points: FloatArray, shape_factor: float = 2.0) -> FloatArray:
    """Moment fit of an ellipse to points ``(..., K, 2)``.

    ``shape_factor`` is 2 for points equally spaced on the boundary and 4 for the pixels
    filling an ellipse. Returns ``(..., 5)`` ellipse parameters.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    out = np.empty((*pts.shape[:-2], 5))
    fit_points(pts.reshape(-1, *pts.shape[-2:]), float(shape_factor), out.reshape(-1, 5))
    return out


def outline_ellipses(
    cameras: tuple[Camera, ...],
    position: FloatArray,
    rotation: FloatArray,
    semi_axes: tuple[float, float, float],
    noise_px: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Closed-form camera ellipses of ellipsoids.

    Parameters
    ----------
    cameras
        ``C`` cameras.
    position: (N, 3)
        Ellipsoid centres in the world.
    rotation: (N, 3, 3)
        Body-to-world rotations.
    semi_axes
        Ellipsoid semi-axes along body x, y, z.
    noise_px: (N, C, K, 2), optional
        Pixel noise added to the ``K = N_BOUNDARY`` distorted outline samples.

    Returns
    -------
    ellipses: (N, C, 5)
    visible: (N, C) bool
        The whole envelope is in front of the camera and the ellipse centre is in the image.
    """
    pos = np.ascontiguousarray(position, dtype=np.float64)
    n, c = pos.shape[0], len(cameras)
    rot = np.ascontiguousarray(rotation, dtype=np.float64)
    noise = np.zeros((n, c, N_BOUNDARY, 2)) if noise_px is None else np.asarray(noise_px, dtype=np.float64)
    for name, arr, shape in (("position", pos, (n, 3)), ("rotation", rot, (n, 3, 3)),
                             ("noise_px", noise, (n, c, N_BOUNDARY, 2))):  # fmt: skip
        if arr.shape != shape:
            raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    axes2 = np.square(np.asarray(semi_axes, dtype=np.float64))
    out, visible = np.zeros((n, c, 5)), np.zeros((n, c), dtype=bool)
    outline_kernel(pos, rot, axes2, *_camera_arrays(cameras),
                   _CIRCLE, np.ascontiguousarray(noise), out, visible)  # fmt: skip
    return out, visible


_ANGLES = np.linspace(0.0, 2 * math.pi, N_BOUNDARY, endpoint=False)
_CIRCLE = np.stack([np.cos(_ANGLES), np.sin(_ANGLES)], axis=-1)  # (K, 2) unit-circle samples


def _camera_arrays(cameras: tuple[Camera, ...]) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Rotations (C, 3, 3), positions (C, 3) and the :data:`~gpbf_env.outline.CAMERA_COLUMNS` (C, 7)."""
    return (
        np.stack([cam.rotation for cam in cameras]).astype(np.float64),
        np.stack([cam.position for cam in cameras]).astype(np.float64),
        np.array([[cam.focal, *cam.principal_point, cam.k1, cam.k2, *cam.size] for cam in cameras]).reshape(
            len(cameras), len(CAMERA_COLUMNS)
        ),
    )
