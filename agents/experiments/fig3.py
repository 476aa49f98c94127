"""Paper Fig. 3: tracking quality against the amount of GP training data.

Dashed lines: exact GPs trained on random subsets of ``n`` points. Solid lines: sparse GPs
with ``m`` pseudo-inputs trained on all points. For each size and repeat (a new random
subset, or a new pseudo-input initialisation) GP-EKF and GP-UKF track the held-out block;
we record the fraction of steps with the truth outside the 3-sigma ellipsoid, whether the
run failed (more than 10% of its steps outside, :func:`estimator_service.tracking.score`), the mean
log-likelihood of the truth and the aggregate RMS.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from agents.experiments.resume import kept
from estimator_service.factory import build_filter
from estimator_service.flight import Flight
from estimator_service.tracking import aggregate_rms, mean_sd, segments, track_flight
from estimator_service.training import TrainSettings, train_models

__all__ = ["data_sparsity", "describe", "plot_data_sparsity", "size_levels"]

FILTERS = ("ekf", "ukf")
MEASURES = ("outside_3sigma", "failed", "mll", "aggregate_rms")


def size_levels(full: int, smallest: int) -> list[int]:
    """Sizes halving from ``full`` down to no fewer than ``smallest``, ascending."""
    out = [full]
    while out[-1] // 2 >= smallest:
        out.append(out[-1] // 2)
    return sorted(out)


def _track(folder: Path, kind: str, test: Flight, seg: int) -> dict[str, dict[str, float]]:
    res = {}
    for filt in FILTERS:
        f = build_filter(filt, kind, folder)
        runs = []
        for r in segments(len(test), seg):
            sc = track_flight(f, test, rows=r).scores()
            sc["aggregate_rms"] = aggregate_rms(sc)
            runs.append(sc)
        res[filt] = {m: float(np.mean([sc[m] for sc in runs])) for m in MEASURES}
    return res


def data_sparsity(
    train: Flight,
    test: Flight,
    settings: TrainSettings,
    *,
    points: Sequence[int],
    pseudo: Sequence[int],
    repeats: int,
    track_seconds: float,
    seed: int = 0,
    tick: Callable[[], None] | None = None,
    cache: Path | None = None,
) -> dict[str, dict[str, dict[str, list[float]]]]:
    """Run both curves; ``{"points"|"pseudo": {size: {filter: {measure: [mean, sd]}}}}``.

    ``cache``: a folder keeping each run's scores (``<curve>_<size>_<repeat>.json``); runs
    already there are not trained again, so an interrupted experiment resumes. The caller
    keeps one cache per set of flights, settings and seed (``reproduce`` checks its folder's
    settings)."""
    seg = round(track_seconds / test.dt)
    jobs = [("points", n, "gp") for n in points] + [("pseudo", m, "sparse") for m in pseudo]
    out: dict[str, dict[str, dict[str, list[float]]]] = {"points": {}, "pseudo": {}}
    for curve, size, kind in jobs:
        runs = []
        for r in range(repeats):
            s = replace(settings, **{"n_points" if curve == "points" else "n_pseudo": size})
            seed_r = seed + 1000 * r + size

            def run(s: TrainSettings = s, kind: str = kind, seed_r: int = seed_r) -> dict:
                with tempfile.TemporaryDirectory(prefix="gpbf-fig3-") as tmp:
                    train_models([train], tmp, kinds=[kind], settings=s, seed=seed_r)
                    return _track(Path(tmp), kind, test, seg)

            runs.append(run() if cache is None else kept(cache / f"{curve}_{size}_{r}.json", run))
            if tick:
                tick()
        out[curve][str(size)] = {f: mean_sd([x[f] for x in runs]) for f in FILTERS}
    return out


def plot_data_sparsity(res: dict, path: Path) -> Path:
    """Two panels like the paper's Fig. 3: steps outside 3 sigma, and MLL, against size."""
    import matplotlib.pyplot as plt

    from estimator_service.plots import save_figure

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    colours = {"ekf": "tab:red", "ukf": "tab:blue"}
    for curve, style, label in (("points", "--", "random subset"), ("pseudo", "-", "sparse")):
        sizes = sorted(res[curve], key=int)
        if not sizes:
            continue
        xs = [int(s) for s in sizes]
        for f in FILTERS:
            for ax, m in zip(axes, ("outside_3sigma", "mll"), strict=True):
                ys = [res[curve][s][f][m][0] for s in sizes]
                ax.plot(xs, ys, style, color=colours[f], marker="o", label=f"GP-{f.upper()}, {label}")
    axes[0].set(
        xlabel="training points / pseudo-inputs", ylabel="steps with truth outside 3 sigma", xscale="log"
    )
    axes[1].set(xlabel="training points / pseudo-inputs", ylabel="mean log-likelihood", xscale="log")
    axes[1].set_ylim(bottom=max(axes[1].get_ylim()[0], -100))
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path)


def describe(res: dict) -> list[str]:
    """Markdown table rows: size, curve, filter and the four measures."""
    lines = [
        "| curve | size | filter | steps outside 3 sigma | failed runs | MLL | aggregate RMS |",
        "| --- | ---: | --- | ---: | ---: | ---: | ---: |",
    ]
    for curve in ("points", "pseudo"):
        for size in sorted(res[curve], key=int):
            for f, v in res[curve][size].items():
                mll = v["mll"][0]
                lines.append(
                    f"| {'random subset' if curve == 'points' else 'sparse'} | {size} | GP-{f.upper()} | "
                    f"{v['outside_3sigma'][0]:.2f} | {v['failed'][0]:.2f} | "
                    f"{mll if math.isfinite(mll) else float('nan'):.1f} | {v['aggregate_rms'][0]:.2f} |"
                )
    return lines
