"""Which model costs the GP filter its angular accuracy: prediction and camera models swapped.

Re-flies the flight of a committed ``gpbf reproduce`` run (same minutes and seed), splits it
into the same folds and tracks each held-out block with the run's models in four
pairings: Param/Param, GP/GP, GP prediction with the parametric camera model and
parametric prediction with the GP camera model. Prints, per pairing, the RMS of each
orientation and angular-velocity axis (RMS over each fold's segments, averaged over the
folds) and ends with one JSON line.

Usage: ``python benchmarks/model_swap.py [--quick] [--results DIR] [--filter ukf]``
(``--quick``: the committed quick run's first fold).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from agents.recorder import collect_flight
from agents.reproduce import split_folds
from agents.tracking import segments, state_error, track_flight
from estimator_service.factory import load_models, make_filter

ROOT = Path(__file__).resolve().parents[1]
PAIRINGS = {  # name: (prediction kind, observation kind)
    "param": ("param", "param"),
    "gp": ("gp", "gp"),
    "gp_pred_param_obs": ("gp", "param"),
    "param_pred_gp_obs": ("param", "gp"),
}
AXES = ("roll", "pitch", "yaw")


def fold_errors(folder: Path, test, filt: str, pred_kind: str, obs_kind: str, seg: int) -> np.ndarray:
    """State errors ``(T, 12)`` of one pairing over the held-out block's segments."""
    pred = load_models(folder, pred_kind)[0]
    obs = load_models(folder, obs_kind)[1]
    f = make_filter(filt, pred, obs)
    runs = [track_flight(f, test, rows=r, rng=np.random.default_rng(0)) for r in segments(len(test), seg)]
    return np.concatenate([state_error(r.mean, r.truth) for r in runs])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the quick run's models, first fold only")
    ap.add_argument("--results", type=Path, default=None, help="a gpbf reproduce output folder")
    ap.add_argument("--filter", default="ukf", choices=("ukf", "ekf"), help="filter to track with")
    args = ap.parse_args()
    results = args.results or ROOT / "docs/results" / ("reproduce_quick" if args.quick else "reproduce_full")
    s = json.loads((results / "results.json").read_text())["settings"]
    flight = collect_flight(s["minutes"] * 60, seed=s["seed"])
    folds = split_folds(flight, s["folds"])[: 1 if args.quick else None]
    seg = round(s["track_seconds"] / flight.metadata["dt"])
    figures: dict[str, float] = {}
    for name, (pk, ok) in PAIRINGS.items():
        per_fold = [fold_errors(results / f"models_fold{i}", test, args.filter, pk, ok, seg)
                    for i, (_, test) in enumerate(folds)]  # fmt: skip
        rms = np.mean([np.sqrt(np.mean(e**2, axis=0)) for e in per_fold], axis=0)  # (12,)
        group = np.mean([math.sqrt(np.mean(e[:, 9:12] ** 2)) for e in per_fold])
        figures[f"{name}_ang_velocity_deg_s"] = round(math.degrees(group), 3)
        for i, axis in enumerate(AXES):
            figures[f"{name}_{axis}_deg"] = round(math.degrees(rms[3 + i]), 3)
            figures[f"{name}_{axis}_rate_deg_s"] = round(math.degrees(rms[9 + i]), 3)
        print(f"{name:20s} pred={pk:6s} obs={ok:6s} angular velocity {math.degrees(group):.2f} deg/s;",
              ", ".join(f"{a} {math.degrees(rms[3 + i]):.2f} deg / {math.degrees(rms[9 + i]):.2f} deg/s"
                        for i, a in enumerate(AXES)))  # fmt: skip
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
