"""Figures of tracking runs (needs the ``plots`` extra, matplotlib; written atomically)."""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from estimator_service.blimp import blimp_system
from estimator_service.files import atomic_write
from estimator_service.tracking import GROUPS, RELIABILITY_LEVELS, TrackResult, reliability

if TYPE_CHECKING:
    from matplotlib.figure import Figure

FloatArray = NDArray[np.float64]

__all__ = [
    "continuous",
    "normalised_path",
    "plot_normalised",
    "plot_reliability",
    "plot_tracking",
    "reliability_path",
    "save_figure",
    "tracking_figure",
]

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


def continuous(values: FloatArray, period: float) -> FloatArray:
    """A time series ``(T,)`` of an angle of period ``period`` without its jumps at the wrap
    (:func:`numpy.unwrap`), to draw as one line; a series with period 0 as it is."""
    return np.unwrap(values, period=period) if period > 0 else values


def plot_tracking(r: TrackResult, path: Path, dt: float | None = None, title: str = "") -> Path:
    """:func:`tracking_figure` written to ``path`` (PNG, atomically)."""
    return save_figure(tracking_figure(r, dt, title), path)


def tracking_figure(r: TrackResult, dt: float | None = None, title: str = "") -> Figure:
    """Estimate vs truth with 3-sigma bands (the blimp: position, yaw and two velocities;
    another system: its first six state components); angles drawn without their wrap, the
    estimate and its band beside the truth by the wrapped error."""
    plt = _pyplot()
    system = r.system
    periods = (system or blimp_system()).state_periods
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
        truth = continuous(r.truth[:, i], periods[i])
        est = truth + r.error[:, i]  # the wrapped error, next to the truth
        ax.fill_between(t, est - 3 * sd, est + 3 * sd, color="tab:blue", alpha=0.25, lw=0, label="3 sigma")
        ax.plot(t, truth, "k", lw=1.0, label="truth")
        ax.plot(t, est, "r--", lw=1.0, label="estimate")
        ax.set_ylabel(label)
    axes[0, 0].legend(loc="upper right", fontsize=8, ncol=3)
    axes[-1, 0].set_xlabel("time (s)")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def normalised_path(path: Path) -> Path:
    """Where :func:`plot_normalised` writes beside a tracking plot ``path``."""
    return path.with_name(f"{path.stem}_normalised{path.suffix or '.png'}")


def plot_normalised(r: TrackResult, path: Path, dt: float | None = None, title: str = "") -> Path:
    """Normalised errors ``error / sd`` of every state component, one panel per state group,
    with the +-3 band a consistent filter stays inside on 99.7 % of steps; each panel's
    title gives the group's fraction of steps with every component inside it."""
    plt = _pyplot()
    system = r.system
    dt = (system.dt if system is not None else 0.25) if dt is None else dt
    groups = (
        [(g.name, list(g.indices)) for g in system.groups]
        if system is not None
        else [(name, list(range(sl.start, sl.stop))) for name, (sl, _) in GROUPS.items()]
    )
    names = system.state if system is not None else tuple(str(i) for i in range(r.mean.shape[1]))
    t = np.arange(len(r.mean)) * dt
    sd = np.sqrt(np.maximum(np.diagonal(r.cov, axis1=1, axis2=2), 1e-300))
    z = r.error / sd
    fig, axes = plt.subplots(
        len(groups), 1, figsize=(10, 1.8 * len(groups) + 0.5), sharex=True, squeeze=False
    )
    for ax, (name, cols) in zip(axes[:, 0], groups, strict=True):
        for c in cols:
            ax.plot(t, z[:, c], lw=0.8, label=names[c])
        ax.axhspan(-3, 3, color="tab:green", alpha=0.1, lw=0)
        inside = float(np.mean(np.all(np.abs(z[:, cols]) <= 3, axis=1)))
        ax.set_title(f"{name}: inside +-3 sd on {inside:.1%} of steps", fontsize=9)
        ax.set_ylabel("error / sd")
        ax.legend(loc="upper right", fontsize=7, ncol=len(cols))
    axes[-1, 0].set_xlabel("time (s)")
    fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)


def reliability_path(path: Path) -> Path:
    """Where :func:`plot_reliability` writes beside a tracking plot ``path``."""
    return path.with_name(f"{path.stem}_reliability{path.suffix or '.png'}")


def plot_reliability(runs: dict[str, TrackResult], path: Path, title: str = "") -> Path:
    """Reliability diagrams: per state group, the observed against the nominal coverage of the
    central intervals of each run's beliefs (:func:`~estimator_service.tracking.reliability`),
    one line per run of ``runs`` (``{label: run}``, all of one system), with the diagonal a
    calibrated belief follows; written to ``path``."""
    plt = _pyplot()
    first = next(iter(runs.values()))
    groups = (first.system or blimp_system()).groups
    fig, axes = plt.subplots(1, len(groups), figsize=(3.2 * len(groups) + 0.4, 3.6), squeeze=False)
    levels = np.asarray(RELIABILITY_LEVELS)
    for label, r in runs.items():
        points = reliability(r.error, r.cov, groups)
        for ax, g in zip(axes[0], groups, strict=True):
            ax.plot(levels, points[g.name], marker="o", ms=3, lw=1, label=label)
    for ax, g in zip(axes[0], groups, strict=True):
        ax.plot([0, 1], [0, 1], "k--", lw=0.8, label="calibrated")
        ax.set(xlim=(0, 1), ylim=(0, 1), xlabel="nominal coverage", title=g.name.replace("_", " "))
        ax.set_aspect("equal")
    axes[0, 0].set_ylabel("observed coverage")
    axes[0, -1].legend(loc="lower right", fontsize=7)
    fig.suptitle(title or "reliability: truth inside the belief's central intervals")
    fig.tight_layout()
    return save_figure(fig, path)
