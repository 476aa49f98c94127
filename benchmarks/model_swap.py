"""Which model costs the GP filter its angular accuracy: prediction and camera models swapped.

Re-flies the flight of a committed ``gpbf reproduce`` run (same minutes and seed), splits it
into the same folds and tracks each held-out block with the run's models in four
pairings: Param/Param, GP/GP, GP prediction with the parametric camera model and
parametric prediction with the GP camera model. Prints, per pairing, the RMS of each
orientation and angular-velocity axis (RMS over each fold's segments, averaged over the
folds) and ends with one JSON line.

Usage: ``python benchmarks/model_swap.py [--quick] [--results DIR] [--filter ukf]``.
The models of a reproduce run are not committed (``.gitignore``): run
``gpbf reproduce --out DIR`` first (about 25 minutes; models byte-identical for a seed).
``--quick`` needs none: it trains tiny param and GP models on a 90-second flight.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

from agents.experiments.reproduce import split_folds
from agents.sim import collect_flight
from estimator_service.factory import load_models, make_filter
from estimator_service.tracking import segments, state_error, track_flight
from estimator_service.training import TrainSettings, train_models

ROOT = Path(__file__).resolve().parents[1]
PAIRINGS = {  # name: (prediction kind, observation kind)
    "param": ("param", "param"),
    "gp": ("gp", "gp"),
    "gp_pred_param_obs": ("gp", "param"),
    "param_pred_gp_obs": ("param", "gp"),
}
AXES = ("roll", "pitch", "yaw")


def fold_errors(f, test, seg: int) -> np.ndarray:
    """State errors ``(T, 12)`` of filter ``f`` over the held-out block's segments."""
    runs = [track_flight(f, test, rows=r, rng=np.random.default_rng(0)) for r in segments(len(test), seg)]
    return np.concatenate([state_error(r.mean, r.truth) for r in runs])


def swap_figures(folders: list[Path], tests: list, filt: str, seg: int) -> dict[str, float]:
    """Per pairing, RMS of each angle and rate (deg, deg/s) and of the angular-velocity group,
    over each fold's segments, averaged over the folds; one line printed per pairing."""
    errors: dict[str, list[np.ndarray]] = {name: [] for name in PAIRINGS}
    for folder, test in zip(folders, tests, strict=True):
        models = {k: load_models(folder, k) for k in ("param", "gp")}  # (prediction, observation)
        for name, (pk, ok) in PAIRINGS.items():
            errors[name].append(fold_errors(make_filter(filt, models[pk][0], models[ok][1]), test, seg))
    figures: dict[str, float] = {}
    for name, per_fold in errors.items():
        pk, ok = PAIRINGS[name]
        rms = np.mean([np.sqrt(np.mean(e**2, axis=0)) for e in per_fold], axis=0)  # (12,)
        group = np.mean([math.sqrt(np.mean(e[:, 9:12] ** 2)) for e in per_fold])
        figures[f"{name}_ang_velocity_deg_s"] = round(math.degrees(group), 3)
        for i, axis in enumerate(AXES):
            figures[f"{name}_{axis}_deg"] = round(math.degrees(rms[3 + i]), 3)
            figures[f"{name}_{axis}_rate_deg_s"] = round(math.degrees(rms[9 + i]), 3)
        print(f"{name:20s} pred={pk:6s} obs={ok:6s} angular velocity {math.degrees(group):.2f} deg/s;",
              ", ".join(f"{a} {math.degrees(rms[3 + i]):.2f} deg / {math.degrees(rms[9 + i]):.2f} deg/s"
                        for i, a in enumerate(AXES)))  # fmt: skip
    return figures


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny models on a 90-second flight")
    ap.add_argument("--results", type=Path, default=Path("out/reproduce"),
                    help="a gpbf reproduce output folder with its models_fold*/ "
                         "(default: gpbf reproduce's own, out/reproduce)")  # fmt: skip
    ap.add_argument("--filter", default="ukf", choices=("ukf", "ekf"), help="filter to track with")
    args = ap.parse_args()
    if args.quick:
        train, test = split_folds(collect_flight(90.0, seed=0), 2)[0]
        with tempfile.TemporaryDirectory() as tmp:
            settings = TrainSettings(n_points=60, n_pseudo=8, restarts=1, max_iter=5, hetero_iterations=1)
            train_models([train], tmp, kinds=("param", "gp"), settings=settings, seed=0)
            figures = swap_figures([Path(tmp)], [test], args.filter, 80)
    else:
        if not (args.results / "results.json").exists():
            sys.exit(f"--results {args.results} has no results.json: run 'gpbf reproduce' first "
                     "(it writes out/reproduce) or give another of its output folders")  # fmt: skip
        s = json.loads((args.results / "results.json").read_text())["settings"]
        folders = [args.results / f"models_fold{i}" for i in range(s["folds"])]
        if missing := [f for f in folders if not (f / "parametric.npz").exists()]:
            sys.exit(f"no models in {missing[0]}: run 'gpbf reproduce --seed {s['seed']} --out "
                     f"{args.results}' first (models are not committed)")  # fmt: skip
        flight = collect_flight(s["minutes"] * 60, seed=s["seed"])
        tests = [test for _, test in split_folds(flight, s["folds"])]
        figures = swap_figures(folders, tests, args.filter, round(s["track_seconds"] / flight.metadata["dt"]))
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
