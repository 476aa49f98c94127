"""Honest beliefs: are the filters sharp and calibrated on flights the models never saw?

Models of each GP kind are trained on one 8-minute flight of the default world and
calibrated by cross-fitting (:mod:`estimator_service.crossfit`: four 2-minute blocks, each
scored with models fitted without it). The filters (factory defaults) then track a new
flight of the training conditions in 30 s runs started at the truth, and so do the same
models without the calibration's noise scales (``build_filter(calibrated=False)``, the
plain filter). With adaptation on they also track new flights of :data:`PERTURBATIONS`,
conditions the models and the adaptation never saw.

Judged (issue 42), per GP filter (EKF and UKF on the gp, egp and sparse models;
:data:`JUDGED_KINDS`), steps of every run pooled:

- ``nees_ratio_min`` / ``_max``: average NEES over the state dimension (1 if consistent),
  targets >= 0.7 and <= 1.5;
- ``coverage2_min`` / ``_max``: per-dimension fraction of steps with the truth within 2
  standard deviations, worst and best dimension (Gaussian 0.954), targets >= 0.90, <= 0.98;
- ``loglik_gain_min``: mean log-likelihood of the truth, calibrated (the factory's filter:
  adapting where the calibration found it helps) minus uncalibrated (plain) (target >= 0);
- ``rms_change_max``: aggregate RMS, calibrated over uncalibrated minus 1 (target <= 0.02);
- ``perturbed_coverage2_min``: ``coverage2_min`` over the perturbed flights, adaptation on
  (target >= 0.85).

``targets_met`` counts the judged figures within their targets (:data:`TARGETS`). The
sparse GP-PF tracks the training conditions too (``pf_within3_min``). Modes: ``--smoke``
(tiny, for the tests), ``--quick`` (200 points, gp and sparse) and the default (paper
size: 900 points, gp, egp, hetgp and sparse; hetGP reported, not judged). The last output
line is one JSON object.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from machine import limits

from agents.sim import collect_flight
from estimator_service.factory import build_filter
from estimator_service.files import atomic_write_text
from estimator_service.filters.adaptive import ADAPT_RATE
from estimator_service.flight import Flight
from estimator_service.plots import plot_reliability
from estimator_service.provenance import code_version, provenance, provenance_line
from estimator_service.tracking import TrackResult, aggregate_rms, coverage_by_sigma, track_flight
from estimator_service.training import TrainSettings, train_models
from gpbf_env.params import BlimpParams

RUN_ROWS = 120  # 30 s runs at 4 Hz
MODES = {  # train s, test s, points, kinds, PF particles, optimiser iterations
    "smoke": (120, 60, 40, ("gp",), 100, 5),
    "quick": (480, 120, 200, ("gp", "sparse"), 500, 40),
    "full": (480, 240, 900, ("gp", "egp", "hetgp", "sparse"), 1000, 100),
}
JUDGED_KINDS = ("gp", "egp", "sparse")  # the GP filters; others are reported beside them
PAYLOAD = 1.05  # a payload of 5 % of the blimp's mass: the weight grows, the buoyant force does not
#: conditions the models never saw (fixed before any result): name -> world options
PERTURBATIONS = {
    "gusts": lambda p: {"params": dataclasses.replace(p, gust_std=3 * p.gust_std)},
    "payload": lambda p: {"params": dataclasses.replace(
        p, mass=p.mass * PAYLOAD, buoyancy_ratio=p.buoyancy_ratio / PAYLOAD)},
    "weak_motor": lambda p: {"params": dataclasses.replace(p, max_main_thrust=0.7 * p.max_main_thrust)},
    "camera_knocked": lambda p: {"camera_knock_deg": 3.0},
    "noisy_camera": lambda p: {"pixel_noise": 2.0},
}  # fmt: skip
#: judged figure -> (lowest, highest) it may take
TARGETS = {
    "nees_ratio_min": (0.7, None), "nees_ratio_max": (None, 1.5),
    "coverage2_min": (0.90, None), "coverage2_max": (None, 0.98),
    "loglik_gain_min": (0.0, None), "rms_change_max": (None, 0.02),
    "perturbed_coverage2_min": (0.85, None),
}  # fmt: skip


def track(filt, flight: Flight, rng: np.random.Generator) -> tuple[dict[str, object], TrackResult]:
    """Scores of ``filt`` over consecutive 30 s runs of ``flight``, their steps pooled, and
    the runs joined into one result (for the reliability figure)."""
    runs = [
        track_flight(filt, flight, rows=slice(a, a + RUN_ROWS), rng=rng)
        for a in range(0, len(flight) - RUN_ROWS + 1, RUN_ROWS)
    ]
    whole = joined(runs)
    return pooled(runs, whole), whole


def joined(runs: list[TrackResult]) -> TrackResult:
    """The runs' steps as one :class:`TrackResult` (step time: their mean)."""
    cat = {k: np.concatenate([getattr(r, k) for r in runs]) for k in ("mean", "cov", "truth", "nis", "dof")}
    diverged = np.concatenate([r.diverged for r in runs])
    return TrackResult(**cat, diverged=diverged, step_s=float(np.mean([r.step_s for r in runs])),
                       system=runs[0].system)  # fmt: skip


def pooled(runs: list[TrackResult], whole: TrackResult) -> dict[str, object]:
    """NEES / n and NIS/dof with the 95 % bands of a consistent filter's averages, mean
    log-likelihood, per-dimension coverage at 1, 2, 3 sigma ``(n,)``, within-3-sigma and
    failed fractions (means over the runs) and aggregate RMS of ``runs``, steps pooled
    (``whole``: the runs :func:`joined`)."""
    scores = [r.scores() for r in runs]
    cover = coverage_by_sigma(whole.error, whole.cov)
    n = whole.error.shape[1]
    out: dict[str, object] = {k: float(np.mean([s[k] for s in scores])) for k in ("within3", "failed", "mll")}
    w = whole.scores()
    out["nees_ratio"] = w["nees"] / n
    out["nees_ratio_band"] = [w["nees_lo"] / n, w["nees_hi"] / n]
    out["nis_per_dof"], out["nis_band"] = w["nis_per_dof"], [w["nis_lo"], w["nis_hi"]]
    out["rms"] = aggregate_rms(w, whole.system.groups if whole.system is not None else None)
    out.update({f"coverage{k}": [round(float(c), 4) for c in v] for k, v in cover.items()})
    return out


def judged(res: dict[tuple[str, str, str], dict], rows: list[tuple[str, str]]) -> dict[str, float]:
    """The issue's figures over ``rows`` (filter, kind) of ``res[filter, kind, world]``."""
    base = [res[f, k, "default"] for f, k in rows]
    raw = [res[f, k, "uncalibrated"] for f, k in rows]
    bent = [res[f, k, w] for f, k in rows for w in PERTURBATIONS]
    return {
        "nees_ratio_min": min(r["nees_ratio"] for r in base),
        "nees_ratio_max": max(r["nees_ratio"] for r in base),
        "coverage2_min": min(min(r["coverage2"]) for r in base),
        "coverage2_max": max(max(r["coverage2"]) for r in base),
        "loglik_gain_min": min(c["mll"] - u["mll"] for c, u in zip(base, raw, strict=True)),
        "rms_change_max": max(c["rms"] / u["rms"] - 1 for c, u in zip(base, raw, strict=True)),
        "perturbed_coverage2_min": min(min(r["coverage2"]) for r in bent),
    }


def met(key: str, value: float) -> bool:
    """Whether the judged figure ``key`` lies within its :data:`TARGETS` bounds."""
    low, high = TARGETS[key]
    return (low is None or value >= low) and (high is None or value <= high)


def evaluate(
    held: Path, kinds: tuple[str, ...], worlds: dict[str, Flight], particles: int
) -> tuple[dict, dict, dict]:
    """Every filter on every world (the perturbed ones with adaptation on), the uncalibrated
    filters on the training conditions, and the PF; ``(res, pf, default)``, ``default`` the
    joined runs of each (filter, kind) in the training conditions."""
    res, default = {}, {}
    for kind in kinds:
        for filt in ("ekf", "ukf"):
            for world, fl in worlds.items():
                on = {} if world == "default" else {"adapt_rate": ADAPT_RATE}
                res[filt, kind, world], run = track(
                    build_filter(filt, kind, held, **on), fl, np.random.default_rng(0)
                )
                if world == "default":
                    default[filt, kind] = run
            res[filt, kind, "uncalibrated"] = track(
                build_filter(filt, kind, held, calibrated=False), worlds["default"], np.random.default_rng(0)
            )[0]
    pf_kinds = [k for k in kinds if k == "sparse" or len(kinds) < 4]  # the exact PF: minutes a run
    pf = {k: track(build_filter("pf", k, held, n_particles=particles), worlds["default"],
                   np.random.default_rng(0))[0] for k in pf_kinds}  # fmt: skip
    return res, pf, default


STATE = ("x", "y", "z", "roll", "pitch", "yaw", "u", "v", "w", "p", "q", "r")


def report(doc: dict, mode: str, judged_kinds: list[str]) -> str:
    """The figures as an outside reader meets them: the judged ones against their targets,
    then per filter and world the consistency measures."""
    summary, runs = doc["summary"], doc["runs"]
    train_s, test_s, points = MODES[mode][:3]
    lines = [
        "# Consistency of the GP filters' beliefs on flights the models never saw",
        "",
        *([provenance_line(doc["provenance"]), ""] if "provenance" in doc else []),
        f"Generated by `benchmarks/bench_consistency.py` ({mode} mode; the numbers in `results.json`). "
        f"Models of each kind ({points} points) trained on one {train_s / 60:g}-minute flight of the default "
        "lab world and calibrated by cross-fitting (four blocks of up to 2 minutes, each scored with models "
        f"fitted without it); the filters track a new {test_s / 60:g}-minute flight of the same conditions "
        "and new "
        "flights of five perturbations, in 30 s runs started at the truth, steps pooled. Nothing here was "
        "tuned on these flights.",
        "",
        f"## Judged figures (EKF and UKF on the {', '.join(judged_kinds)} models)",
        "",
        "| figure | measured | target | met |",
        "|---|---|---|---|",
    ]
    for key, (low, high) in TARGETS.items():
        bound = f">= {low}" if high is None else f"<= {high}"
        lines.append(
            f"| {key} | {summary[key]:.4f} | {bound} | {'yes' if met(key, summary[key]) else 'no'} |"
        )
    lines += [
        "",
        "NEES / n: the average normalised estimation error squared over the 12 state dimensions "
        "(1 for a consistent belief); coverage at k sigma: the fraction of steps with the truth within "
        "k standard deviations, per dimension (Gaussian: 0.683, 0.954, 0.997); log-likelihood: the mean "
        "log density of the truth under the belief (the paper's Table 8 measure, higher is better); "
        "uncalibrated: the same models without the calibration's noise scales, plain filter. The gain and "
        "the RMS change compare what a user gets from the model folder (calibrated, adapting where the "
        "calibration found it helps) with what the models give without any calibration.",
        "",
        "## Per filter and world",
        "",
        "| filter | model | world | NEES / n [95 % band] | NIS / dof [95 % band] | log-likelihood "
        "| worst dimension at 1 / 2 / 3 sigma | aggregate RMS |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for key, r in sorted(runs.items()):
        filt, kind, world = key.split("/")
        world = "default, uncalibrated" if world == "uncalibrated" else world.replace("_", " ")
        worst = [
            f"{STATE[int(np.argmin(r[f'coverage{k}']))]} {min(r[f'coverage{k}']):.3f}" for k in (1, 2, 3)
        ]
        lo, hi = r["nees_ratio_band"]
        nlo, nhi = r["nis_band"]
        nees = f"{r['nees_ratio']:.2f} [{lo:.2f}, {hi:.2f}]"
        nis = f"{r['nis_per_dof']:.2f} [{nlo:.2f}, {nhi:.2f}]"
        lines.append(f"| {filt.upper()} | {kind} | {world} | {nees} | {nis} | {r['mll']:.2f} | "
                     f"{' / '.join(worst)} | {r['rms']:.2f} |")  # fmt: skip
    lines += ["", "Perturbations (with the filters' adaptation on): " + ", ".join(doc["perturbations"]) + ".",
              "", "![reliability](reliability.png)", ""]  # fmt: skip
    return "\n".join(lines)


def write_report(out: Path, doc: dict, judged_kinds: list[str]) -> None:
    """``report.md`` beside ``out``, with ``notes.md`` there (what the figures say, written
    after the run) appended."""
    notes = out.parent / "notes.md"
    extra = "\n" + notes.read_text() if notes.exists() else ""
    atomic_write_text(out.parent / "report.md", report(doc, doc["summary"]["mode"], judged_kinds) + extra)


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="200-point models (a few minutes)")
    parser.add_argument("--smoke", action="store_true", help="tiny run that only checks it works (tests)")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON figures here")
    parser.add_argument("--models", type=Path, default=None, help="keep the trained models in this folder")
    parser.add_argument("--reuse", action="store_true", help="track with the models already in --models")
    parser.add_argument("--report-only", action="store_true", help="rewrite report.md beside --out from it")
    parser.add_argument("--seed-offset", type=int, default=0,
                        help="other flights (e.g. to decide a design on flights no report uses)")  # fmt: skip
    args = parser.parse_args(argv)
    if args.report_only and args.out:
        doc = json.loads(args.out.read_text())
        write_report(args.out, doc, sorted({key.split("/")[1] for key in doc["runs"]} & set(JUDGED_KINDS)))
        return doc["summary"]
    start, code = time.monotonic(), code_version()  # the code that runs, not the checkout at the end
    mode = "smoke" if args.smoke else "quick" if args.quick else "full"
    train_s, test_s, points, kinds, particles, iters = MODES[mode]
    p = BlimpParams()
    seed = 21 + args.seed_offset
    train = collect_flight(train_s, seed=seed)
    worlds = {"default": collect_flight(test_s, seed=seed + 1)}
    for i, (name, options) in enumerate(PERTURBATIONS.items()):
        worlds[name] = collect_flight(test_s, seed=seed + 2 + i, env_kwargs=options(p))
    s = TrainSettings(n_points=points, max_iter=iters, sparse_iter=min(120, iters), calibration_seconds=120)
    with tempfile.TemporaryDirectory() as tmp:
        held = args.models or Path(tmp) / "held_out"
        if not (args.reuse and args.models):
            train_models([train], held, kinds=list(kinds), settings=s)
        calibration = json.loads((held / "calibration.json").read_text())
        res, pf, default_runs = evaluate(held, kinds, worlds, particles)
    for (filt, kind, world), r in [
        *sorted(res.items()),
        *(((("pf", k, "default"), r) for k, r in pf.items())),
    ]:
        two = f"{min(r['coverage2']):.3f}-{max(r['coverage2']):.3f}"
        print(f"{filt.upper():3s} {kind:6s} {world:14s}: NEES/n {r['nees_ratio']:6.2f}  2-sigma {two}  "
              f"mll {r['mll']:8.2f}  RMS {r['rms']:7.2f}")  # fmt: skip
    rows = [(f, k) for k in kinds if k in JUDGED_KINDS or mode == "smoke" for f in ("ekf", "ukf")]
    figures = judged(res, rows)
    default = [*(res[f, k, "default"] for f, k in rows), *pf.values()]
    out = {
        "mode": mode,
        **{k: round(v, 4) for k, v in figures.items()},
        "targets_met": sum(met(k, v) for k, v in figures.items()),
        "targets": len(TARGETS),
        "within3_min": round(min(res[f, k, "default"]["within3"] for f, k in rows), 4),
        "pf_within3_min": round(min(r["within3"] for r in pf.values()), 4),
        "failed_runs_max": round(max(r["failed"] for r in default), 4),
    }  # fmt: skip
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        doc = {"summary": out, "targets": TARGETS, "perturbations": list(PERTURBATIONS),
               "runs": {"/".join(k): v for k, v in res.items()}, "pf": pf,
               "calibration": calibration.get("details", {}).get("noise"),
               "provenance": provenance(time.monotonic() - start, code=code)}  # fmt: skip
        atomic_write_text(args.out, json.dumps(doc, indent=1) + "\n")
        write_report(args.out, doc, sorted({k for _, k in rows}))
        judged_runs = {f"{k.upper()}-{f.upper()}": default_runs[f, k] for f, k in rows}
        plot_reliability(judged_runs, args.out.parent / "reliability.png",
                         title="Reliability on a new flight of the training conditions")  # fmt: skip
    out.update(limits())  # this machine's dgemm rate and read bandwidth, for the ratios
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
