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
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from agents.experiments.resume import kept
from estimator_service.factory import build_filter
from estimator_service.flight import Flight
from estimator_service.tracking import aggregate_rms, mean_sd, segment_rows, segments, track_flight
from estimator_service.training import TrainSettings, train_models
from estimator_service.work import part_weights, track_seconds

__all__ = [
    "Fig3Run",
    "describe",
    "fig3_runs",
    "fig3_table",
    "plot_data_sparsity",
    "size_levels",
]

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
        ok = [sc["mll"] for sc in runs if not sc["failed"]]  # the paper's MLL: successful runs only
        res[filt]["mll_successful"] = float(np.mean(ok)) if ok else math.nan
        res[filt]["successful_runs"] = float(len(ok))
    return res


@dataclass(frozen=True)
class Fig3Run:
    """One point of a curve: ``kind`` models trained with ``settings`` (``seed``) on
    ``train``, GP-EKF and GP-UKF tracking ``test`` in segments of ``seg`` rows; scores kept
    at ``cache`` (None: not kept). Calling it returns ``{filter: {measure: value}}``."""

    curve: str
    size: int
    repeat: int
    kind: str
    settings: TrainSettings
    seed: int
    train: Flight
    test: Flight
    seg: int
    cache: Path | None

    @property
    def kept_at(self) -> Path | None:
        """Where the run's scores are kept (None: not kept)."""
        return None if self.cache is None else self.cache / f"{self.curve}_{self.size}_{self.repeat}.json"

    def __call__(self) -> dict[str, dict[str, float]]:
        if self.kept_at is None:
            return self._run()
        return kept(self.kept_at, self._run)

    def seconds(self) -> float:
        """Estimated seconds of the run (:mod:`estimator_service.work`); 0 when kept."""
        if self.kept_at is not None and self.kept_at.exists():
            return 0.0
        steps = segment_rows(len(self.test), self.seg)
        track = sum(track_seconds([self.train], self.kind, self.settings, f, steps) for f in FILTERS)
        return sum(part_weights([self.train], [self.kind], self.settings)) + track

    def _run(self) -> dict[str, dict[str, float]]:
        with tempfile.TemporaryDirectory(prefix="gpbf-fig3-") as tmp:
            train_models([self.train], tmp, kinds=[self.kind], settings=self.settings, seed=self.seed)
            return _track(Path(tmp), self.kind, self.test, self.seg)


def fig3_runs(
    train: Flight, test: Flight, settings: TrainSettings, *, points: Sequence[int], pseudo: Sequence[int],
    repeats: int, track_seconds: float, seed: int = 0, cache: Path | None = None,
) -> list[Fig3Run]:  # fmt: skip
    """Every run of both curves, the largest first (the longest, for a pool of workers).

    ``cache``: a folder keeping each run's scores (``<curve>_<size>_<repeat>.json``); runs
    already there are not trained again, so an interrupted experiment resumes. The caller
    keeps one cache per set of flights, settings and seed (``reproduce`` checks its folder's
    settings)."""
    seg = round(track_seconds / test.dt)
    curves = [("points", n, "gp") for n in points] + [("pseudo", m, "sparse") for m in pseudo]
    runs = []
    for curve, size, kind in curves:
        s = replace(settings, **{"n_points" if curve == "points" else "n_pseudo": size})
        runs += [Fig3Run(curve, size, r, kind, s, seed + 1000 * r + size, train, test, seg, cache)
                 for r in range(repeats)]  # fmt: skip
    return sorted(runs, key=lambda run: -run.size if run.curve == "points" else 0)


def fig3_table(
    runs: Sequence[Fig3Run], results: Sequence[dict]
) -> dict[str, dict[str, dict[str, dict[str, list[float]]]]]:
    """``{"points"|"pseudo": {size: {filter: {measure: [mean, sd]}}}}`` over the repeats."""
    by_point: dict[tuple[str, int], list[dict]] = {}
    for run, res in zip(runs, results, strict=True):
        by_point.setdefault((run.curve, run.size), []).append(res)
    out: dict = {"points": {}, "pseudo": {}}
    for (curve, size), res in sorted(by_point.items(), key=lambda kv: (kv[0][0], kv[0][1])):
        out[curve][str(size)] = {
            f: {
                **mean_sd([{m: x[f][m] for m in MEASURES} for x in res]),
                "mll_successful": _successful_mll(res, f),
            }
            for f in FILTERS
        }
    return out


def _successful_mll(res: Sequence[dict], f: str) -> list[float]:
    """``[mean, sd]`` over the repeats of filter ``f``'s mean log-likelihood of its successful
    tracking runs, weighted by their number (the paper's Fig. 3 measure beside the failed
    runs); NaN when every run failed (or the repeats predate the measure)."""
    pairs = [(x[f]["mll_successful"], x[f]["successful_runs"]) for x in res if x[f].get("successful_runs")]
    if not pairs:
        return [math.nan, math.nan]
    v, w = np.array(pairs).T
    mean = float(np.average(v, weights=w))
    return [mean, float(np.sqrt(np.average((v - mean) ** 2, weights=w)))]


def _number(v: float | None) -> float:
    """A figure read back from ``results.json`` (null: not measured, e.g. no successful run)."""
    return math.nan if v is None else float(v)


def plot_data_sparsity(res: dict, path: Path) -> Path:
    """The paper's Fig. 3: the percentage of failed runs, and the mean log-likelihood of the
    successful runs, against the number of training points or pseudo-inputs."""
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
            row = [res[curve][s][f] for s in sizes]
            failed = [100 * v["failed"][0] for v in row]
            mll = [_number(v.get("mll_successful", v["mll"])[0]) for v in row]  # older results: all runs
            for ax, ys in zip(axes, (failed, mll), strict=True):
                ax.plot(xs, ys, style, color=colours[f], marker="o", label=f"GP-{f.upper()}, {label}")
    axes[0].set(xlabel="training points / pseudo-inputs", ylabel="failed runs (%)", xscale="log")
    axes[1].set(xlabel="training points / pseudo-inputs", ylabel="mean log-likelihood, successful runs",
                xscale="log")  # fmt: skip
    axes[0].legend(fontsize=8, handlelength=4)  # long enough to tell dashed from solid
    fig.tight_layout()
    return save_figure(fig, path)


def describe(res: dict) -> list[str]:
    """Markdown table rows: size, curve, filter and the measures (the mean log-likelihood over
    all runs and over the successful ones)."""
    lines = [
        "| curve | size | filter | steps outside 3 sigma | failed runs | MLL | MLL, successful runs | "
        "aggregate RMS |",
        "| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for curve in ("points", "pseudo"):
        for size in sorted(res[curve], key=int):
            for f, v in res[curve][size].items():
                mll, ok = _number(v["mll"][0]), _number(v.get("mll_successful", [math.nan])[0])  # older: none
                lines.append(
                    f"| {'random subset' if curve == 'points' else 'sparse'} | {size} | GP-{f.upper()} | "
                    f"{v['outside_3sigma'][0]:.2f} | {v['failed'][0]:.2f} | "
                    f"{mll if math.isfinite(mll) else float('nan'):.1f} | {ok:.1f} | "
                    f"{v['aggregate_rms'][0]:.2f} |"
                )
    return lines
