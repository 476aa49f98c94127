"""The rendered camera mode: silhouette images of the envelope and the ellipse fitted to
them by background subtraction, as the paper's cameras did (see :mod:`gpbf_env.camera`)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from gpbf_env.camera import Camera, ellipse_from_points

__all__ = ["background_image", "fit_ellipse_image", "render_frame", "silhouette_mask"]

FloatArray = NDArray[np.float64]


def silhouette_mask(
    cam: Camera, position: FloatArray, rotation: FloatArray, semi_axes: tuple[float, float, float]
) -> NDArray[np.bool_]:
    """Pixels whose (distorted) ray hits the ellipsoid, ``(H, W)`` bool."""
    inv_axes = 1.0 / np.asarray(semi_axes, dtype=np.float64)
    to_unit = inv_axes[:, None] * rotation.T  # world -> unit-sphere frame
    origin = to_unit @ (cam.position - position)
    dirs = cam.pixel_rays @ (to_unit @ cam.rotation.T).T
    od = dirs @ origin
    disc = od * od - np.sum(dirs * dirs, axis=1) * (origin @ origin - 1.0)
    hit = (disc >= 0.0) & (od < 0.0)
    w, h = cam.size
    return hit.reshape(h, w)


def background_image(cam: Camera) -> NDArray[np.float64]:
    """A fixed, textured background (walls and floor) for ``cam``, grey levels ``(H, W)``."""
    w, h = cam.size
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    return 70.0 + 40.0 * vv / h + 12.0 * np.sin(uu / 23.0) * np.cos(vv / 31.0)


def render_frame(
    cam: Camera,
    position: FloatArray,
    rotation: FloatArray,
    semi_axes: tuple[float, float, float],
    rng: np.random.Generator | None = None,
    noise_std: float = 4.0,
) -> NDArray[np.uint8]:
    """Grey image ``(H, W)`` of the envelope (bright) over the background, with pixel noise."""
    img = background_image(cam)
    img[silhouette_mask(cam, position, rotation, semi_axes)] = 215.0
    if rng is not None and noise_std > 0:
        img = img + rng.normal(0.0, noise_std, size=img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def fit_ellipse_image(
    cam: Camera, frame: NDArray[np.uint8], threshold: float = 40.0, min_pixels: int = 20
) -> FloatArray | None:
    """Background subtraction and a moment ellipse fit; ``None`` when nothing is seen."""
    fg = np.abs(frame.astype(np.float64) - background_image(cam)) > threshold
    vv, uu = np.nonzero(fg)
    if uu.size < min_pixels:
        return None
    pts = np.stack([uu, vv], axis=-1).astype(np.float64)
    return ellipse_from_points(pts, 4.0)
