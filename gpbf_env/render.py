"""``rgb_array`` rendering: camera views with ellipses overlaid, and a top-down map."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gpbf_env.camera import euler_to_matrix
from gpbf_env.core import WorldConfig
from gpbf_env.imaging import render_frame

__all__ = ["draw_ellipse", "render_scene"]

RED = np.array([230, 40, 40], dtype=np.uint8)
BLUE = np.array([40, 90, 230], dtype=np.uint8)
GREEN = np.array([30, 170, 60], dtype=np.uint8)


def draw_ellipse(
    img: NDArray[np.uint8], ellipse: NDArray[Any], color: NDArray[np.uint8], scale: float = 1.0
) -> None:
    """Draw the outline of ``(cx, cy, width, height, angle)`` into ``img`` (H, W, 3) in place."""
    cx, cy, w, h, ang = (float(v) for v in ellipse)
    t = np.linspace(0, 2 * math.pi, 400)
    x = cx + 0.5 * w * np.cos(t) * math.cos(ang) - 0.5 * h * np.sin(t) * math.sin(ang)
    y = cy + 0.5 * w * np.cos(t) * math.sin(ang) + 0.5 * h * np.sin(t) * math.cos(ang)
    _plot_points(img, x * scale, y * scale, color)


def _plot_points(img: NDArray[np.uint8], x: NDArray[Any], y: NDArray[Any], color: NDArray[np.uint8]) -> None:
    xi, yi = np.rint(x).astype(int), np.rint(y).astype(int)
    keep = (xi >= 0) & (xi < img.shape[1]) & (yi >= 0) & (yi < img.shape[0])
    img[yi[keep], xi[keep]] = color


def _camera_views(
    cfg: WorldConfig, state: NDArray[np.float64], obs: dict[str, Any] | None
) -> NDArray[np.uint8]:
    rot = euler_to_matrix(state[None, 3:6])[0]
    views = []
    for k, cam in enumerate(cfg.cameras):
        grey = render_frame(cam, state[:3], rot, cfg.semi_axes)[::2, ::2]
        img = np.repeat(grey[:, :, None], 3, axis=2)
        if obs is not None and obs["valid"][k]:
            draw_ellipse(img, obs["ellipses"][k], RED, scale=0.5)
        img[:, -1] = 255
        views.append(img)
    return np.concatenate(views, axis=1)


def _top_down(
    cfg: WorldConfig,
    state: NDArray[np.float64],
    trail: NDArray[np.float64],
    goal: NDArray[np.float64],
    width: int,
) -> NDArray[np.uint8]:
    lx, ly, _ = cfg.room
    s = (width - 20) / lx
    h = int(ly * s) + 20
    img = np.full((h, width, 3), 245, dtype=np.uint8)
    img[10 : h - 10, [10, width - 11]] = 0
    img[[10, h - 11], 10 : width - 10] = 0

    def to_px(x: NDArray[Any], y: NDArray[Any]) -> tuple[NDArray[Any], NDArray[Any]]:
        return 10 + x * s, h - 10 - y * s

    if len(trail):
        _plot_points(img, *to_px(trail[:, 0], trail[:, 1]), BLUE)
    gx, gy = to_px(np.array([goal[0]]), np.array([goal[1]]))
    for d in range(-6, 7):
        _plot_points(img, gx + d, gy + d, GREEN)
        _plot_points(img, gx + d, gy - d, GREEN)
    t = np.linspace(0, 2 * math.pi, 200)
    yaw = state[5]
    a, b = cfg.semi_axes[0], cfg.semi_axes[1]
    ex = state[0] + a * np.cos(t) * math.cos(yaw) - b * np.sin(t) * math.sin(yaw)
    ey = state[1] + a * np.cos(t) * math.sin(yaw) + b * np.sin(t) * math.cos(yaw)
    _plot_points(img, *to_px(ex, ey), RED)
    nose = np.linspace(0, 1.2 * a, 50)
    _plot_points(img, *to_px(state[0] + nose * math.cos(yaw), state[1] + nose * math.sin(yaw)), RED)
    return img


def render_scene(
    cfg: WorldConfig,
    state: NDArray[np.float64],
    obs: dict[str, Any] | None,
    trail: NDArray[np.float64],
    goal: NDArray[np.float64],
) -> NDArray[np.uint8]:
    """Camera views (half size, last reported ellipses in red) above a top-down room map.

    Returns
    -------
    image: (H, W, 3) uint8
    """
    views = _camera_views(cfg, state, obs)
    top = _top_down(cfg, state, trail, goal, views.shape[1])
    return np.ascontiguousarray(np.concatenate([views, top], axis=0))
