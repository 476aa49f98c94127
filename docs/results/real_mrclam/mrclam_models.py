"""The UTIAS MRCLAM robots' models as a user writes them for gpbf: a unicycle driven by the
commanded forward and angular velocity, and a camera's range and bearing to a surveyed
landmark. Named in ``mrclam.json`` as ``mrclam_models:<function>``; the folder holding this
file must be importable (on ``PYTHONPATH``)."""

import numpy as np


def unicycle(x, u, p, dt):
    """Next states (M, 3) of states x (M, 3) = (x, y, heading) under commands u (M, 2) = (v, w);
    p["k_v"], p["k_w"]: gains from the commanded to the real velocities (fitted)."""
    v, w, h = p["k_v"] * u[:, 0], p["k_w"] * u[:, 1], x[:, 2]
    return np.stack([x[:, 0] + v * np.cos(h) * dt, x[:, 1] + v * np.sin(h) * dt, h + w * dt], axis=1)


def unicycle_noise(x, u, p, dt):
    """The shape of the unicycle's noise standard deviation per step (M, 3): growing with the
    commanded speeds, 0.1 |v| dt + 1 mm in position and 0.1 |w| dt + 0.002 rad in heading (a
    textbook odometry model); training fits one factor per component."""
    pos = 0.1 * np.abs(u[:, 0]) * dt + 0.001
    return np.stack([pos, pos, 0.1 * np.abs(u[:, 1]) * dt + 0.002], axis=1)


def range_bearing(x, c, p):
    """Range (m) and bearing (rad, wrapped) of the landmark at (c["lx"], c["ly"]) seen from
    states x (M, 3); p["range_bias"]: the camera's range offset (fitted)."""
    dx, dy = c["lx"] - x[:, 0], c["ly"] - x[:, 1]
    bearing = np.arctan2(dy, dx) - x[:, 2]
    return np.stack([np.hypot(dx, dy) + p["range_bias"], (bearing + np.pi) % (2 * np.pi) - np.pi], axis=1)


def range_bearing_jacobian(x, c, p):
    """d (range, bearing) / d state (M, 2, 3)."""
    dx, dy = c["lx"] - x[:, 0], c["ly"] - x[:, 1]
    q = dx * dx + dy * dy
    r = np.sqrt(q)
    zero = np.zeros_like(r)
    return np.stack(
        [np.stack([-dx / r, -dy / r, zero], axis=1), np.stack([dy / q, -dx / q, zero - 1.0], axis=1)], axis=1
    )
