"""Figures shared by the CLI and the experiments (written atomically)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from agents.tracking import TrackResult

__all__ = ["plot_tracking", "save_figure"]

PANELS = (
    (0, "x (m)"),
    (1, "y (m)"),
    (2, "z (m)"),
    (5, "yaw (rad)"),
    (6, "u (m/s)"),
    (11, "r (rad/s)"),
)


def save_figure(fig: plt.Figure, path: Path, dpi: int = 110) -> Path:
    """Save to a temporary file beside ``path``, then rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".png", dir=path.parent)
    os.close(fd)
    fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    os.replace(tmp, path)
    return path


def plot_tracking(r: TrackResult, path: Path, dt: float = 0.25, title: str = "") -> Path:
    """Estimate vs truth with 3-sigma bands for position, yaw and two velocities."""
    t = np.arange(len(r.mean)) * dt
    fig, axes = plt.subplots(len(PANELS), 1, figsize=(10, 11), sharex=True)
    for ax, (i, label) in zip(axes, PANELS, strict=True):
        sd = np.sqrt(r.cov[:, i, i])
        est = r.truth[:, i] + r.error[:, i]  # unwrapped next to the truth
        ax.fill_between(t, est - 3 * sd, est + 3 * sd, color="tab:blue", alpha=0.25, lw=0, label="3 sigma")
        ax.plot(t, r.truth[:, i], "k", lw=1.0, label="truth")
        ax.plot(t, est, "r--", lw=1.0, label="estimate")
        ax.set_ylabel(label)
    axes[0].legend(loc="upper right", fontsize=8, ncol=3)
    axes[-1].set_xlabel("time (s)")
    fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)
