"""Figures of tracking runs (needs the ``plots`` extra, matplotlib; written atomically)."""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from estimator_service.files import atomic_write
from estimator_service.tracking import TrackResult

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["plot_tracking", "save_figure"]

#: the blimp's panels: position, yaw and two velocities
BLIMP_PANELS = (
    (0, "x (m)"),
    (1, "y (m)"),
    (2, "z (m)"),
    (5, "yaw (rad)"),
    (6, "u (m/s)"),
    (11, "r (rad/s)"),
)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Figure, path: Path, dpi: int = 110) -> Path:
    """Render ``fig`` to PNG and write it atomically; the figure is closed."""
    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, format="png")
    _pyplot().close(fig)
    return atomic_write(path, lambda fh: fh.write(buf.getvalue()))


def plot_tracking(r: TrackResult, path: Path, dt: float | None = None, title: str = "") -> Path:
    """Estimate vs truth with 3-sigma bands (the blimp: position, yaw and two velocities;
    another system: its first six state components)."""
    plt = _pyplot()
    system = r.system
    if dt is None:
        dt = system.dt if system is not None else 0.25
    if system is None or system.name == "blimp":
        panels = BLIMP_PANELS
    else:
        panels = tuple(enumerate(system.state[:6]))
    t = np.arange(len(r.mean)) * dt
    fig, axes = plt.subplots(
        len(panels), 1, figsize=(10, 1.8 * len(panels) + 0.5), sharex=True, squeeze=False
    )
    for ax, (i, label) in zip(axes[:, 0], panels, strict=True):
        sd = np.sqrt(r.cov[:, i, i])
        est = r.truth[:, i] + r.error[:, i]  # unwrapped next to the truth
        ax.fill_between(t, est - 3 * sd, est + 3 * sd, color="tab:blue", alpha=0.25, lw=0, label="3 sigma")
        ax.plot(t, r.truth[:, i], "k", lw=1.0, label="truth")
        ax.plot(t, est, "r--", lw=1.0, label="estimate")
        ax.set_ylabel(label)
    axes[0, 0].legend(loc="upper right", fontsize=8, ncol=3)
    axes[-1, 0].set_xlabel("time (s)")
    fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)
