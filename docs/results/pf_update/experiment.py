"""The particle filter's update on flights no report uses: Table 1's likelihood weights
against the bridged update (Frei & Kuensch 2013), per model kind.

    python docs/results/pf_update/experiment.py --seed 2 --kinds param,gp,egp --out <folder>

The protocol is the reproduce report's PF rows, fixed before any result (``README.md`` in
this folder states each decision rule with the time it was written): the lab world's
20-minute flight of ``--seed``, four contiguous folds of which ``--folds`` are used,
paper-size models trained on each fold's training part (``ReproduceSettings``), then every
120-s test segment's first 30 s tracked by a 500-particle PF with each update rule and three
random streams (``seed``, ``seed + 1``, ``seed + 2``). Models are kept in ``--out`` and
reused when the command is run again. Writes ``rows.json`` (one row per run) and prints a
summary per kind and rule, its last line one JSON object. ``--quick``: a small version for
the smoke test.

``--trace FOLD,SEGMENT,STREAM --kinds KIND --rule RULE`` follows one run step by step instead
(``--out`` a folder with that fold's models, such as a ``gpbf reproduce`` folder of the same
seed): per camera step the error of the predicted and updated position means (mm), their
spreads (mean position standard deviation, mm), the weights' effective sample size and the
innovation's NIS per degree of freedom; its last line one JSON object with the largest
errors and the smallest effective sample size.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from agents.experiments.reproduce import ReproduceSettings, split_folds
from agents.experiments.resume import trained
from agents.sim import collect_flight
from estimator_service.factory import build_filter
from estimator_service.files import atomic_write_text
from estimator_service.filters import GaussianBelief
from estimator_service.filters.particle import UPDATE_RULES
from estimator_service.gp.linalg import single_threaded_blas
from estimator_service.tracking import _default_init_std, aggregate_rms, segments, track_flight
from estimator_service.training import train_models

RULES = UPDATE_RULES
STREAMS = 3  # random streams per segment
MEANS = ("rms", "mll", "nees", "coverage2_min")  # the figures averaged over a kind's runs


def settings(args: argparse.Namespace) -> ReproduceSettings:
    s = ReproduceSettings.quick() if args.quick else ReproduceSettings()
    return replace(s, seed=args.seed, kinds=tuple(args.kinds))


def _folds(s: ReproduceSettings) -> list:
    """The (train, test) flights of the seed's folds, as the reproduce report splits them."""
    return split_folds(collect_flight(s.minutes * 60, seed=s.seed, env_kwargs=s.world), s.folds)


def _pf_segments(test, s: ReproduceSettings) -> list[slice]:
    """The report's PF rows: each ``track_seconds`` segment's first ``pf_seconds``."""
    seg = round(s.track_seconds / test.dt)
    return segments(len(test), seg, min(seg, round(s.pf_seconds / test.dt)))


def run(args: argparse.Namespace) -> list[dict]:
    """Train (or reuse) each fold's models and track its segments with both rules."""
    s = settings(args)
    folds, rows = _folds(s), []
    for fold in args.folds:
        train, test = folds[fold]
        folder = args.out / f"models_fold{fold}"
        if not trained(folder):
            train_models([train], folder, kinds=s.kinds, settings=s.train_settings(), seed=s.seed + fold)
        for kind in s.kinds:
            for rule in RULES:
                filt = build_filter("pf", kind, folder, n_particles=s.particles, update_rule=rule)
                for i, rows_i in enumerate(_pf_segments(test, s)):
                    for k in range(1 if args.quick else STREAMS):
                        rows.append(one(filt, test, rows_i, s.seed + k) | {
                            "fold": fold, "kind": kind, "rule": rule, "segment": i, "stream": s.seed + k,
                        })  # fmt: skip
                        print(json.dumps(rows[-1]), flush=True)
    return rows


def one(filt, test, rows, stream: int) -> dict:
    with single_threaded_blas():
        sc = track_flight(filt, test, rows=rows, rng=np.random.default_rng(stream)).scores()
    keys = ("mll", "nees", "coverage2_min", "step_ms")
    return {"rms": aggregate_rms(sc), **{k: sc[k] for k in keys}}


def summary(rows: list[dict]) -> dict:
    """Per kind and rule: mean aggregate RMS (mm-deg units), its worst run, mean held-out
    log-likelihood of the truth, mean NEES (12 if consistent), mean worst-dimension 2-sigma
    coverage; and per kind the bridge's RMS ratio and log-likelihood gain."""
    out: dict = {}
    for kind in dict.fromkeys(r["kind"] for r in rows):
        per = {}
        for rule in RULES:
            rs = [r for r in rows if r["kind"] == kind and r["rule"] == rule]
            per[rule] = {k: float(np.mean([r[k] for r in rs])) for k in MEANS}
            per[rule] |= {"runs": len(rs), "rms_worst": float(np.max([r["rms"] for r in rs]))}
        per["bridge_rms_ratio"] = per["bridge"]["rms"] / per["table1"]["rms"]
        per["bridge_mll_gain"] = per["bridge"]["mll"] - per["table1"]["mll"]
        out[kind] = per
    return out


def trace(args: argparse.Namespace) -> dict:
    """One run of ``--trace``, step by step (see the module's docstring)."""
    s = settings(args)
    fold, segment, stream = args.trace
    test = _folds(s)[fold][1]
    segs = _pf_segments(test, s)
    if segment >= len(segs):
        raise SystemExit(f"--trace: the fold has {len(segs)} segments, got segment {segment}")
    fl = test.select(np.arange(len(test))[segs[segment]])
    filt = build_filter("pf", args.kinds[0], args.out / f"models_fold{fold}", n_particles=s.particles,
                        update_rule=args.rule)  # fmt: skip
    rng = np.random.default_rng(stream)
    start = GaussianBelief(fl.state[0].copy(), np.diag(_default_init_std(fl) ** 2))  # as track_flight
    belief = filt.initial(start, rng)
    valid, worst = fl.expand_valid(), {"prior_mm": 0.0, "post_mm": 0.0, "ess_min": float(s.particles)}
    with single_threaded_blas():
        for k in range(len(fl) - 1):
            prior = filt.predict(belief, fl.control[k], rng)
            belief, info = filt.update(prior, fl.z[k + 1], valid[k + 1], rng)
            if not info.dof:
                continue
            (e0, s0), (e1, s1) = (_position(filt.gaussian(b), fl.state[k + 1]) for b in (prior, belief))
            print(f"step {k + 1:3d}: prior error {e0:7.1f} mm, sd {s0:5.1f} | updated error {e1:7.1f} mm, "
                  f"sd {s1:5.1f} | ESS {info.ess:6.1f} | NIS/dof {info.nis / info.dof:6.2f}")  # fmt: skip
            worst = {"prior_mm": max(worst["prior_mm"], e0), "post_mm": max(worst["post_mm"], e1),
                     "ess_min": min(worst["ess_min"], info.ess)}  # fmt: skip
    return {"trace": list(args.trace), "kind": args.kinds[0], "rule": args.rule, **worst}


def _position(g: GaussianBelief, truth: np.ndarray) -> tuple[float, float]:
    """Position error of the mean and mean position standard deviation, both in mm."""
    sd = np.sqrt(np.diag(g.cov)[:3]).mean()
    return float(np.linalg.norm(g.mean[:3] - truth[:3]) * 1e3), float(sd * 1e3)


def _count(v: str) -> int:
    n = int(v)
    if n < 0:
        raise ValueError(v)
    return n


def _counts(v: str) -> list[int]:
    return [_count(f) for f in v.split(",")]


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seed", type=_count, required=True, help="the flight's seed (no report's: 0 and 1 are)")
    p.add_argument("--kinds", type=lambda v: v.split(","), default=["param", "gp", "egp"], help="model kinds")
    p.add_argument("--folds", type=_counts, default=[0, 1], help="folds (of 4; quick: of 2)")
    p.add_argument("--out", type=Path, required=True, help="folder for the models and rows.json")
    p.add_argument("--quick", action="store_true", help="a small version (smoke test)")
    p.add_argument(
        "--trace", type=_counts, default=None, help="FOLD,SEGMENT,STREAM: follow one run step by step"
    )
    p.add_argument("--rule", choices=RULES, default="table1", help="the update rule --trace follows")
    args = p.parse_args(argv)
    nfolds = settings(args).folds
    if any(f >= nfolds for f in args.folds) or (args.trace is not None and args.trace[0] >= nfolds):
        p.error(f"--folds/--trace: a fold must be below {nfolds}")
    if args.trace is not None and len(args.trace) != 3:
        p.error(f"--trace: FOLD,SEGMENT,STREAM (three integers), got {args.trace}")
    if args.trace is not None:
        res = trace(args)
        print(json.dumps(res))
        return res
    t0 = time.perf_counter()
    rows = run(args)
    res = {"seed": args.seed, "folds": args.folds, "quick": args.quick, "summary": summary(rows),
           "seconds": round(time.perf_counter() - t0, 1)}  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "rows.json", json.dumps(rows, indent=1) + "\n")
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
