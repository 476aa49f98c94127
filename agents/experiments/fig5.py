"""Fig. 5 of the paper: the tracking uncertainty of a heteroscedastic GP against a regular GP
while the tail motor runs.

The paper (Sect. 6.3.2): the heteroscedastic GP's uncertainty rises when the tail motor is
active and varies with it, most in the sideways and rotational velocities; the regular GP's
does not. Here both GP-UKFs track the same held-out flight; the figures are, per model and
per state of :data:`FIG5_STATES`, the mean standard deviation while the tail motor is active
(``|tail command| >`` :data:`TAIL_ACTIVE`) and while it is not, and the coefficient of
variation of the standard deviation over the active steps.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from estimator_service.factory import build_filter
from estimator_service.flight import Flight
from estimator_service.tracking import track_flight
from estimator_service.training import prediction_data

__all__ = ["FIG5_STATES", "TAIL_ACTIVE", "fig5"]

#: the states the paper names as most affected: the body-frame sideways velocity ``v`` and the
#: rotational velocities ``p, q, r`` (``gpbf_env.STATE_NAMES``)
FIG5_STATES = {"v": 7, "p": 9, "q": 10, "r": 11}
#: the tail command above which (in magnitude) the tail motor counts as active (Fig. 4's threshold)
TAIL_ACTIVE = 0.3
TAIL = 2  # the tail motor's column of the controls
MODELS = ("hetgp", "gp")


def fig5(folder: Path, test: Flight, path: Path) -> dict[str, float]:
    """GP-UKF standard deviations of :data:`FIG5_STATES` over ``test`` with the ``hetgp`` and
    ``gp`` models of ``folder``, the tail power shaded (the figure at ``path``); figures
    ``"<model> <state>: ..."`` for the report and its checks. Empty without an active step
    or an inactive one among those tracked (the flight's first episode)."""
    import matplotlib.pyplot as plt

    from estimator_service.plots import save_figure

    tail = np.abs(test.control[:-1, TAIL])
    filters = {kind: build_filter("ukf", kind, folder) for kind in MODELS}
    runs = {kind: (f, track_flight(f, test)) for kind, f in filters.items()}
    tracked = len(runs[MODELS[0]][1].mean)  # the steps of the flight's first episode
    tail = tail[:tracked]
    on = tail > TAIL_ACTIVE
    if on.all() or not on.any():
        return {}
    n = test.state.shape[1]
    inp, change = prediction_data([test.select(np.arange(tracked + 1))])  # the transitions tracked
    t = np.arange(tracked) * test.dt
    res: dict[str, float] = {}
    fig, axes = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    for ax, kind in zip(axes, MODELS, strict=True):
        ukf, r = runs[kind]
        for shade in np.unique(np.round(tail, 1)):  # intensity: the tail's power
            ax.fill_between(t, 0, 1, where=np.round(tail, 1) == shade, color="0.5",
                            alpha=0.5 * float(shade), lw=0, transform=ax.get_xaxis_transform())  # fmt: skip
        one = ukf.prediction.predict(inp[:, :n], inp[:, n:])
        for name, i in FIG5_STATES.items():
            sd = np.sqrt(r.cov[:, i, i])
            ax.plot(t, sd / sd.mean(), lw=0.8, label=name)
            res[f"{kind} {name}: sd while the tail is active"] = float(sd[on].mean())
            res[f"{kind} {name}: sd otherwise"] = float(sd[~on].mean())
            res[f"{kind} {name}: sd variation while the tail is active"] = float(sd[on].std() / sd[on].mean())
            res |= _one_step(kind, name, one.mean[:, i] - change[:, i], one.var[:, i], on)
        ax.set(ylabel="sd / its mean", title=f"GP-UKF, {kind} (shading: tail motor power)")
    axes[0].legend(loc="upper right", fontsize=8, ncol=4)
    axes[-1].set_xlabel("time (s)")
    fig.tight_layout()
    save_figure(fig, path)
    return res


def _one_step(kind: str, name: str, err: np.ndarray, var: np.ndarray, on: np.ndarray) -> dict[str, float]:
    """The prediction model's one-step RMS error and RMS predicted sd, tail active over the
    rest: how much the tail motor changes the motion's noise, and what the model learned of it."""
    root_mean = lambda sq: float(np.sqrt(np.mean(sq)))  # noqa: E731  (of squares, or of variances)
    sq, key = err * err, f"{kind} {name}: one-step"
    return {
        f"{key} error, tail active over the rest": root_mean(sq[on]) / root_mean(sq[~on]),
        f"{key} predicted sd, tail active over the rest": root_mean(var[on]) / root_mean(var[~on]),
    }
