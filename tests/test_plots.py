"""Figures: angles drawn without their wrap, every line labelled, the demo's camera view."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from estimator_service.angles import wrap_angle
from estimator_service.plots import continuous, tracking_figure
from estimator_service.tracking import TrackResult


def _yaw_through_the_wrap(t: int = 80) -> np.ndarray:
    """States ``(t, 12)`` whose yaw turns through +-pi twice."""
    x = np.zeros((t, 12))
    x[:, 0] = np.linspace(0, 2, t)
    x[:, 5] = wrap_angle(np.linspace(2.5, 2.5 + 4 * math.pi, t))
    return x


def _lines(ax) -> list:
    return [ln for ln in ax.get_lines() if len(ln.get_xdata()) > 1]


def test_the_tracking_figure_draws_the_yaw_without_its_wrap() -> None:
    truth = _yaw_through_the_wrap()
    mean = truth.copy()
    mean[:, 5] = wrap_angle(truth[:, 5] + 0.05)  # the estimate sits across the wrap from the truth at times
    cov = np.tile(np.eye(12) * 1e-3, (len(truth), 1, 1))
    r = TrackResult(mean, cov, truth, np.zeros(80), np.zeros(80, np.int64), np.zeros(80, bool), 0.0)
    fig = tracking_figure(r, 0.25)
    yaw = next(ax for ax in fig.axes if ax.get_ylabel() == "yaw (rad)")
    truth_line, est_line = _lines(yaw)
    assert np.abs(np.diff(truth_line.get_ydata())).max() < 0.3  # no 2 pi jumps
    np.testing.assert_allclose(est_line.get_ydata() - truth_line.get_ydata(), 0.05, atol=1e-9)
    np.testing.assert_allclose(wrap_angle(truth_line.get_ydata()), truth[:, 5], atol=1e-12)
    assert all(not a.get_label().startswith("_") for ax in fig.axes for a in [*_lines(ax), *ax.collections])


def test_the_demo_figures_label_every_line_and_draw_the_yaw_without_its_wrap(tmp_path: Path) -> None:
    from agents.demo import plot_camera_views, service_tracking_figure

    truth = _yaw_through_the_wrap()
    log = {"truth": truth, "dt": 0.25, "egp": wrap_angle(truth + 0.1), "egp_var": np.full((80, 12), 1e-3)}
    fig = service_tracking_figure(log, ("egp",))
    yaw = fig.axes[2]
    truth_line, est_line = _lines(yaw)
    assert np.abs(np.diff(est_line.get_ydata())).max() < 0.3
    np.testing.assert_allclose(est_line.get_ydata() - truth_line.get_ydata(), 0.1, atol=1e-9)
    for ax in fig.axes:
        labels = {a.get_label() for a in [*_lines(ax), *ax.collections]}
        assert labels == {"truth", "UKF / egp", "3 sigma / egp"} and ax.get_legend() is not None
    path = tmp_path / "views.png"
    plot_camera_views(np.array([5.0, 3.0, 1.6, 0.0, 0.0, 0.4, 0, 0, 0, 0, 0, 0]), path)
    assert path.stat().st_size > 10_000


def test_continuous_unwraps_angles_only() -> None:
    a = wrap_angle(np.linspace(0, 10, 50))
    np.testing.assert_allclose(continuous(a, 2 * math.pi), np.linspace(0, 10, 50), atol=1e-12)
    assert continuous(a, 0.0) is a
