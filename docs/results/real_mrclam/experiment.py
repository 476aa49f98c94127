"""gpbf on a real robot: UTIAS MRCLAM Dataset 6 (Leung et al., IJRR 2011), against a
textbook EKF with the surveyed landmark map and against dead reckoning.

    PYTHONPATH=docs/results/real_mrclam python docs/results/real_mrclam/experiment.py

Everything is fixed before the held-out part is seen (see ``report.md``): robot 1's event
log is aligned to 0.1 s steps with the control delay that best predicts the *training*
part's motion; models train on the first 70 % of the run (900 points per GP, the user's
unicycle and range-bearing models of ``mrclam_models.py`` fitted by training, no noise
calibration) and are scored on the last 30 %; across runs, the same models track robot 2's
last 30 %. Writes ``results.json`` (last line of stdout too), ``report.md`` and plots.
``--quick`` runs a small version for the smoke test.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # mrclam_models, as a user's PYTHONPATH would

from estimator_service.events import align, load_event_csv  # noqa: E402
from estimator_service.factory import build_filter, load_models, make_filter, warm_up  # noqa: E402
from estimator_service.files import atomic_write_text  # noqa: E402
from estimator_service.flight import Flight  # noqa: E402
from estimator_service.models.calibration import calibration_choices  # noqa: E402
from estimator_service.plots import plot_reliability  # noqa: E402
from estimator_service.provenance import code_version, provenance, provenance_line  # noqa: E402
from estimator_service.system import System  # noqa: E402
from estimator_service.tracking import TrackResult, coverage_by_sigma, track_flight  # noqa: E402
from estimator_service.training import TrainSettings, train_models  # noqa: E402

DATASET = "UTIAS MRCLAM Dataset 6 (Leung, Halpern, Barfoot, Liu, IJRR 2011), robot 1; across runs robot 2"
TRAIN_FRACTION = 0.7
DELAYS = tuple(np.round(np.arange(0.0, 0.45, 0.05), 2))  # candidate control delays (s)
KINDS = ("param", "gp", "egp", "hetgp", "sparse")
FILTERS = ("ekf", "ukf", "pf")
INIT_STD = np.array([0.01, 0.01, math.radians(1.0)])  # start: the truth, 1 cm, 1 cm, 1 deg
PARTICLES = 500  # 2,000 took over 0.4 s per step with a 900-point GP here: 500 keeps the run under an hour
# the textbook EKF's process noise per step: std = a |command| dt + c (x, y: a_v, c_xy; heading: a_w, c_h)
TEXTBOOK_Q = {"a_v": 0.1, "c_xy": 0.001, "a_w": 0.1, "c_h": 0.002}


def wrap(a):
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi


def unicycle_step(x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """The plain unicycle on the commands (rows of x (M, 3), u (M, 2))."""
    h = x[:, 2]
    return np.stack(
        [x[:, 0] + u[:, 0] * np.cos(h) * dt, x[:, 1] + u[:, 0] * np.sin(h) * dt, wrap(h + u[:, 1] * dt)], 1
    )


def choose_delay(log, system: System) -> tuple[float, dict[str, list[float]]]:
    """The control delay whose aligned training part the plain unicycle predicts best one
    step ahead (sum over x, y, heading of the RMS relative to no delay)."""
    table = {}
    for d in DELAYS:
        f, _ = align(log, control_delay=float(d))
        x, u, xn = train_part(f).transitions()
        table[str(d)] = np.sqrt(
            np.mean(system.state_error(unicycle_step(x, u, system.dt), xn) ** 2, 0)
        ).tolist()
    base = np.array(table[str(DELAYS[0])])
    best = min(DELAYS, key=lambda d: float(np.sum(np.array(table[str(d)]) / base)))
    return float(best), table


def train_part(f: Flight) -> Flight:
    return f.select(np.arange(int(TRAIN_FRACTION * len(f))))


def test_part(f: Flight) -> Flight:
    return f.select(np.arange(int(TRAIN_FRACTION * len(f)), len(f)))


def tracked(filt, f: Flight, system: System, **options) -> TrackResult:
    """``track_flight`` from the true start after one warm-up step, as the service warms a
    filter when it loads its models: the models' caches (the exact GPs' inverse factors) are
    built before the timed steps."""
    warm_up(filt, system)
    return track_flight(filt, f, init_std=INIT_STD, **options)


#: the diagnosis: EKFs on one kind's prediction model and another's observation model
MIXED_KINDS = ("param", "egp", "hetgp")


def mixed(test: Flight, system: System, models: Path) -> dict[str, dict]:
    """Position RMS, heading RMS, NEES / 3 and mean log-likelihood of EKFs on every pairing of
    ``MIXED_KINDS``' calibrated prediction and observation models (without adaptation): which
    half of a kind its accuracy comes from. Computed on the held-out part after the run, a
    diagnosis only: nothing is chosen by it."""
    loaded = {k: load_models(models, k) for k in MIXED_KINDS}
    out = {}
    for p in MIXED_KINDS:
        for o in MIXED_KINDS:
            f = figures(tracked(make_filter("ekf", loaded[p][0], loaded[o][1], system=system), test, system))
            out[f"{p}+{o}"] = {k: f[k] for k in ("position_rms_cm", "heading_rms_deg", "nees_ratio", "mll")}
    return out


def figures(r: TrackResult) -> dict[str, float]:
    """Position RMS per axis (cm), heading RMS (deg), NEES, mean log-likelihood, coverage at
    1, 2, 3 sigma per dimension (worst), ms per step."""
    s = r.scores()
    e = r.error
    out = {
        "position_rms_cm": float(100 * np.sqrt(np.mean(e[:, :2] ** 2))),
        "heading_rms_deg": float(np.degrees(np.sqrt(np.mean(e[:, 2] ** 2)))),
        "nees": s["nees"],
        "nees_ratio": s["nees"] / 3,
        "mll": s["mll"],
        "ms_per_step": r.step_s * 1e3,
        "diverged_steps": s["diverged_steps"],
    }
    for k, cover in coverage_by_sigma(e, r.cov).items():
        out[f"coverage{k}"] = [round(float(c), 4) for c in cover]
    return out


def textbook(f: Flight, train: Flight, system: System) -> tuple[dict, np.ndarray, np.ndarray]:
    """A textbook EKF: the unicycle on the commands, range-bearing to the surveyed map, R
    from the training readings' residuals against the truth, Q of TEXTBOOK_Q."""
    lm = np.array([s.constants for s in system.sensors])
    res = []
    for k in range(system.n_sensors):
        xs, zs = train.readings(k)
        dx, dy = lm[k, 0] - xs[:, 0], lm[k, 1] - xs[:, 1]
        res.append(
            np.column_stack([zs[:, 0] - np.hypot(dx, dy), wrap(zs[:, 1] - np.arctan2(dy, dx) + xs[:, 2])])
        )
    r_cov = np.diag(np.concatenate(res).std(axis=0) ** 2)
    s, p, dt = f.state[0].copy(), np.diag(INIT_STD**2), system.dt
    means, covs = [], []
    t0 = time.perf_counter()
    for k in range(len(f) - 1):
        v, w = f.control[k]
        jac = np.array([[1, 0, -v * math.sin(s[2]) * dt], [0, 1, v * math.cos(s[2]) * dt], [0, 0, 1]])
        s = unicycle_step(s[None], f.control[k][None], dt)[0]
        qxy = TEXTBOOK_Q["a_v"] * abs(v) * dt + TEXTBOOK_Q["c_xy"]
        qh = TEXTBOOK_Q["a_w"] * abs(w) * dt + TEXTBOOK_Q["c_h"]
        p = jac @ p @ jac.T + np.diag([qxy**2, qxy**2, qh**2])
        for j in np.flatnonzero(f.valid[k + 1]):
            z = f.z[k + 1, system.sensor_slice(j)]
            dx, dy = lm[j, 0] - s[0], lm[j, 1] - s[1]
            q = dx * dx + dy * dy
            h = np.array([[-dx / math.sqrt(q), -dy / math.sqrt(q), 0], [dy / q, -dx / q, -1]])
            innov = np.array([z[0] - math.sqrt(q), wrap(z[1] - math.atan2(dy, dx) + s[2])])
            gain = p @ h.T @ np.linalg.inv(h @ p @ h.T + r_cov)
            s = s + gain @ innov
            s[2] = wrap(s[2])
            p = (np.eye(3) - gain @ h) @ p
        means.append(s.copy())
        covs.append(p.copy())
    step_s = (time.perf_counter() - t0) / max(1, len(f) - 1)
    r = TrackResult(np.array(means), np.array(covs), f.state[1:], np.zeros(len(means)),
                    np.zeros(len(means), np.int64), np.zeros(len(means), bool), step_s, system)  # fmt: skip
    return figures(r), r.mean, r.cov


def dead_reckoning(f: Flight, system: System) -> dict:
    s, out = f.state[0].copy(), []
    for k in range(len(f) - 1):
        s = unicycle_step(s[None], f.control[k][None], system.dt)[0]
        out.append(s)
    e = system.state_error(np.array(out), f.state[1:])
    return {"position_rms_cm": float(100 * np.sqrt(np.mean(e[:, :2] ** 2))),
            "heading_rms_deg": float(np.degrees(np.sqrt(np.mean(e[:, 2] ** 2))))}  # fmt: skip


def run(out: Path, quick: bool, reuse: bool = False) -> dict:
    start, code = time.monotonic(), code_version()  # the code that runs, not the checkout at the end
    system = System.from_json((HERE / "mrclam.json").read_text())
    log1 = load_event_csv(HERE / "data" / "robot1.events.csv.gz", system)
    log2 = load_event_csv(HERE / "data" / "robot2.events.csv.gz", system)
    delay, delay_table = choose_delay(log1, system)
    f1, report1 = align(log1, control_delay=delay)
    f2, _ = align(log2, control_delay=delay)
    train, test, other = train_part(f1), test_part(f1), test_part(f2)
    kinds, filters = (("param", "egp"), ("ekf",)) if quick else (KINDS, FILTERS)
    if quick:
        test, other = test.select(np.arange(300)), other.select(np.arange(300))
    settings = TrainSettings()  # the defaults a user gets (900 points, calibration on 120 s blocks)
    if quick:
        settings = TrainSettings(n_points=150, restarts=1, max_iter=30, calibration_seconds=20)
    models, timing_file = out / "models", out / "models" / "train_seconds.json"
    if reuse and timing_file.exists():  # the models of an earlier run of the same experiment
        timings = json.loads(timing_file.read_text())
        train_s = timings.pop("total")
    else:
        t0 = time.perf_counter()
        timings = train_models([train], models, kinds=kinds, settings=settings)
        train_s = time.perf_counter() - t0
        atomic_write_text(timing_file, json.dumps({**timings, "total": train_s}))
    print("trained", round(train_s, 1), json.dumps(calibration_choices(models)), flush=True)
    rows, results = {}, {}
    for kind in kinds:
        for filt in filters:
            options = {"n_particles": 200 if quick else PARTICLES} if filt == "pf" else {}
            filt_ = build_filter(filt, kind, models, **options)
            r = tracked(filt_, test, system, rng=np.random.default_rng(0))
            rows[f"{kind}_{filt}"] = figures(r)
            print(f"{kind}_{filt}", json.dumps(rows[f"{kind}_{filt}"]), flush=True)
            results[f"{kind}_{filt}"] = r
    for kind in kinds:  # the same models without their noise calibration (floors kept)
        r = tracked(build_filter("ekf", kind, models, calibrated=False), test, system)
        rows[f"{kind}_ekf_uncalibrated"] = figures(r)
    book, book_mean, book_cov = textbook(test, train, system)
    cross = {}
    for kind in kinds:
        r = tracked(build_filter("ekf", kind, models), other, system)
        cross[f"{kind}_ekf"] = figures(r)
    cross["textbook_ekf"] = textbook(other, train, system)[0]
    cross["dead_reckoning"] = dead_reckoning(other, system)
    diagnosis = {} if quick else mixed(test, system, models)
    egp = rows["egp_ekf"]
    summary = {
        "egp_ekf_rms_ratio_to_textbook": egp["position_rms_cm"] / book["position_rms_cm"],
        "egp_ekf_nees_ratio": egp["nees_ratio"],
        "egp_ekf_ms_per_step": egp["ms_per_step"],
        "egp_ekf_position_rms_cm": egp["position_rms_cm"],
        "textbook_ekf_position_rms_cm": book["position_rms_cm"],
        "textbook_ekf_nees_ratio": book["nees_ratio"],
    }
    result = {
        "summary": summary,
        "consistency": consistency(rows),
        "dataset": DATASET,
        "control_delay_s": delay,
        "delay_one_step_rms": delay_table,
        "alignment": {
            "rows": report1.rows,
            "readings_first": sum(report1.first.values()),
            "readings_extra": sum(report1.extra.values()),
            "readings_dropped": sum(report1.dropped.values()),
        },
        "train_rows": len(train),
        "test_rows": len(test),
        "test_seconds": round(len(test) * system.dt, 1),
        "train_seconds": round(train_s, 1),
        "train_seconds_per_kind": {k: round(v, 1) for k, v in timings.items()},
        "held_out": {**rows, "textbook_ekf": book, "dead_reckoning": dead_reckoning(test, system)},
        "across_runs_robot2": cross,
        "calibration": calibration_choices(models),
        "diagnosis_prediction_x_observation": diagnosis,
        "fitted": json.loads((models / "parametric.json").read_text())
        if (models / "parametric.json").exists()
        else None,
        "quick": quick,
        "provenance": provenance(time.monotonic() - start, code=code),
    }
    atomic_write_text(out / "results.json", json.dumps(result, indent=1) + "\n")
    atomic_write_text(out / "report.md", report(result))
    if not quick:
        n = len(book_mean)
        book_run = TrackResult(book_mean, book_cov, test.state[1 : n + 1], np.zeros(n), np.zeros(n, np.int64),
                               np.zeros(n, bool), 0.0, system)  # fmt: skip
        runs = {"EGP-EKF": results["egp_ekf"], "hetGP-EKF": results["hetgp_ekf"], "textbook EKF": book_run}
        plot(out, system, test, results["egp_ekf"], book_mean, book_cov, models)
        plot_reliability(runs, out / "reliability.png", title="Reliability on the held-out part of robot 1")
    return result


#: the consistency figures over the GP filters (EKF and UKF on the gp, egp and sparse models), as the
#: lab world's consistency report gives them; the calibration's gain and cost from the EKFs
CONSISTENCY_FILTERS = tuple(f"{k}_{f}" for k in ("gp", "egp", "sparse") for f in ("ekf", "ukf"))


def consistency(held: dict[str, dict]) -> dict[str, float]:
    """NEES / 3 and per-dimension coverage at 2 sigma (worst, best) over
    :data:`CONSISTENCY_FILTERS`; calibrated minus uncalibrated mean log-likelihood (smallest)
    and calibrated over uncalibrated position RMS minus 1 (largest) over the EKFs of every
    kind that has both."""
    rows = [held[k] for k in CONSISTENCY_FILTERS if k in held]
    pairs = [(held[f"{k}_ekf"], held[f"{k}_ekf_uncalibrated"]) for k in KINDS
             if f"{k}_ekf" in held and f"{k}_ekf_uncalibrated" in held]  # fmt: skip
    if not rows or not pairs:
        return {}
    return {
        "nees_ratio_min": min(r["nees_ratio"] for r in rows),
        "nees_ratio_max": max(r["nees_ratio"] for r in rows),
        "coverage2_min": min(min(r["coverage2"]) for r in rows),
        "coverage2_max": max(max(r["coverage2"]) for r in rows),
        "loglik_gain_min": min(c["mll"] - u["mll"] for c, u in pairs),
        "rms_change_max": max(c["position_rms_cm"] / u["position_rms_cm"] - 1 for c, u in pairs),
    }


TARGETS = {  # the issue's judged figures: (bound, direction)
    "egp_ekf_rms_ratio_to_textbook": "<= 0.85",
    "egp_ekf_nees_ratio": "0.7 - 1.5",
    "egp_ekf_ms_per_step": "<= 1",
}


def _met(key: str, value: float) -> bool:
    return {"egp_ekf_rms_ratio_to_textbook": value <= 0.85, "egp_ekf_nees_ratio": 0.7 <= value <= 1.5,
            "egp_ekf_ms_per_step": value <= 1.0}[key]  # fmt: skip


def _row(name: str, f: dict) -> str:
    if "nees" not in f:  # dead reckoning: no belief
        return f"| {name} | {f['position_rms_cm']:.1f} | {f['heading_rms_deg']:.2f} | | | | | |"
    cover = " / ".join(f"{min(f[f'coverage{k}']):.2f}" for k in (1, 2, 3))
    return (f"| {name} | {f['position_rms_cm']:.1f} | {f['heading_rms_deg']:.2f} | {f['nees_ratio']:.2f} | "
            f"{f['mll']:.2f} | {cover} | {f['ms_per_step']:.2f} | {int(f['diverged_steps'])} |")  # fmt: skip


HEADER = (
    "| method | position RMS per axis (cm) | heading RMS (deg) | NEES / 3 | mean log-likelihood | "
    "coverage at 1 / 2 / 3 sigma, worst dimension | ms per step | diverged steps |\n"
    "|---|---|---|---|---|---|---|---|"
)


def report(r: dict) -> str:
    """report.md from results.json: what was run, the judged figures, every filter and kind."""
    s, a = r["summary"], r["alignment"]
    lines = [
        "# gpbf on a real robot: UTIAS MRCLAM Dataset 6",
        "",
        *([provenance_line(r["provenance"]), ""] if "provenance" in r else []),
        "Generated by `experiment.py` beside this file"
        + (" (QUICK smoke-test run)" if r["quick"] else "")
        + ".",
        "",
        "## What was run",
        "",
        f"- Data: {r['dataset']}. Wheeled robots; Vicon ground truth (x, y, heading) at ~64 Hz; the "
        "commanded forward and angular velocities at ~67 Hz; camera range-bearing readings of 15 surveyed "
        "landmarks. Citation: K. Y. K. Leung, Y. Halpern, T. D. Barfoot, H. H. T. Liu, *The UTIAS "
        "Multi-Robot Cooperative Localization and Mapping Dataset*, IJRR 30(8), 2011. `convert.py` turns the "
        "original files into the event logs in `data/`.",
        f"- Alignment to 0.1 s steps by gpbf's one rule (`estimator_service.events`): {a['rows']} steps, "
        f"{a['readings_first']} landmark readings ({a['readings_extra']} second readings within a step, "
        f"{a['readings_dropped']} outside the steps). Control delay {r['control_delay_s']} s: the one (of "
        "0-0.4 s) whose aligned *training* part the plain unicycle predicts best one step ahead "
        "(`delay_one_step_rms` in results.json).",
        f"- Split: train on the first 70 % ({r['train_rows']} steps), score on the last 30 % "
        f"({r['test_rows']} steps, {r['test_seconds']} s). Across runs: the same models on robot 2's "
        "last 30 %.",
        "- gpbf: the description `mrclam.json` with the user's models of `mrclam_models.py` (unicycle with "
        "fitted velocity gains; range-bearing with a fitted range bias; the 15 landmarks one sensor type "
        "whose constants are their surveyed positions; the unicycle's noise shaped as the textbook EKF's, "
        "0.1 |command| dt + (1 mm, 1 mm, 0.002 rad), with one fitted factor per state: "
        "`mrclam_models.unicycle_noise`), noise floors 5 cm / 0.01 rad per reading and "
        "1 mm / 1 mm / 0.002 rad per step, `gpbf train`'s defaults (900 points per GP, noise calibration "
        "cross-fitted on four 120 s blocks of the training part and chosen by their held-out "
        "log-likelihood, refused where it scores worse than none); filters as `gpbf track` builds them "
        "(EKF and UKF adapt their process noise where the calibration chose to; PF with 500 particles). "
        "Every filter starts at the "
        "truth with standard deviations 1 cm, 1 cm, 1 deg.",
        "- Textbook EKF: the unicycle on the commands, range-bearing to the surveyed map, measurement "
        "noise from the training readings' residuals against the truth, process noise per step "
        "std = 0.1 |command| dt + (1 mm, 1 mm, 0.002 rad), fixed before any run. Dead reckoning: the "
        "unicycle on the commands from the true start.",
        f"- Training took {r['train_seconds']} s ("
        + ", ".join(f"{k} {v} s" for k, v in r["train_seconds_per_kind"].items())
        + ").",
        "",
        "Measures (held-out part): position RMS per axis, heading RMS, NEES / 3 (1 for a consistent "
        "belief), the mean log-likelihood of the truth under the belief (higher is better; rewards "
        "calibration and sharpness together), the fraction of steps with the truth within 1, 2 and 3 "
        "standard deviations on the worst of the three dimensions (a Gaussian: 0.68 / 0.95 / 0.997), "
        "and the filter's time per step on this 2-core machine.",
        "",
        "## Judged figures",
        "",
        "| figure | value | target | met |",
        "|---|---|---|---|",
    ]
    for key, bound in TARGETS.items():
        lines.append(f"| `{key}` | {s[key]:.3g} | {bound} | {'yes' if _met(key, s[key]) else '**no**'} |")
    if r.get("consistency"):
        c = r["consistency"]
        lines += ["", "## Consistency of the GP filters (held-out part)", "",
                  "Over the EKF and UKF on the `gp`, `egp` and `sparse` models (as the lab world's "
                  "consistency report); the calibration's gain and cost over the EKFs of all five kinds, "
                  "each against the same models uncalibrated.", "",
                  "| figure | value | a consistent, never-worse calibration |", "|---|---|---|",
                  f"| NEES / 3, smallest and largest | {c['nees_ratio_min']:.2f} - {c['nees_ratio_max']:.2f} "
                  "| 0.7 - 1.5 |",
                  f"| coverage at 2 sigma, worst and best dimension | {c['coverage2_min']:.3f} - "
                  f"{c['coverage2_max']:.3f} | 0.90 - 0.98 |",
                  "| mean log-likelihood, calibrated minus uncalibrated, smallest | "
                  f"{c['loglik_gain_min']:.2f} | >= 0 |",
                  "| position RMS, calibrated over uncalibrated minus 1, largest | "
                  f"{c['rms_change_max']:+.3f} | <= 0.02 |"]  # fmt: skip
    lines += ["", "## Held-out part of robot 1", "", HEADER]
    held = r["held_out"]
    for name in (
        "dead_reckoning",
        "textbook_ekf",
        *[k for k in held if k not in ("dead_reckoning", "textbook_ekf")],
    ):
        lines.append(_row(name.replace("_", " "), held[name]))
    lines += ["", "## Across runs: models of robot 1, robot 2's last 30 %", "", HEADER]
    for name, f in r["across_runs_robot2"].items():
        lines.append(_row(name.replace("_", " "), f))
    lines += ["", "## Noise calibration chosen on the training part", "",
              "| kind | applied | family | factor | held-out log-likelihood | uncalibrated | reason |",
              "|---|---|---|---|---|---|---|"]  # fmt: skip
    for kind, c in r["calibration"].items():
        lines.append(f"| {kind} | {c['applied']} | {c['family']} | {c['factor']} | {c['heldout_mll']} | "
                     f"{c['uncalibrated_mll']} | {c['reason']} |")  # fmt: skip
    if r.get("diagnosis_prediction_x_observation"):
        lines += _diagnosis(r["diagnosis_prediction_x_observation"])
    notes = HERE / "notes.md"
    if notes.exists() and not r["quick"]:
        lines += ["", notes.read_text().strip()]
    lines += ["", "Plots: `trajectory.png` (EGP-EKF with 3-sigma bands), `errors.png` (error over time, "
              "EGP-EKF and the textbook EKF), `landmark_residuals.png` (held-out readings minus the fitted "
              "range-bearing model at the truth, per landmark), `reliability.png` (observed against nominal "
              "coverage of the beliefs' central intervals per state group: EGP-EKF, hetGP-EKF, textbook "
              "EKF; on the diagonal when calibrated, below it when overconfident).", ""]  # fmt: skip
    return "\n".join(lines)


def _diagnosis(d: dict[str, dict]) -> list[str]:
    lines = ["", "## Diagnosis: which model makes a kind accurate", "",
             "EKFs on one kind's prediction model and another kind's observation model (both calibrated, "
             "no adaptation), on the held-out part of robot 1. Computed after the run to explain it; "
             "nothing was chosen by it.", "",
             "| prediction model | observation model | position RMS per axis (cm) | heading RMS (deg) | "
             "NEES / 3 | mean log-likelihood |", "|---|---|---|---|---|---|"]  # fmt: skip
    for key, f in d.items():
        p, o = key.split("+")
        lines.append(f"| {p} | {o} | {f['position_rms_cm']:.1f} | {f['heading_rms_deg']:.2f} | "
                     f"{f['nees_ratio']:.2f} | {f['mll']:.2f} |")  # fmt: skip
    return lines


def plot(
    out: Path, system: System, test: Flight, egp: TrackResult, book_mean, book_cov, models: Path
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from estimator_service.factory import load_parametric

    t = test.t[1:] - test.t[0]
    names, units, scale = ("x", "y", "heading"), ("m", "m", "deg"), (1.0, 1.0, 180 / math.pi)
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for i, ax in enumerate(axes):
        sd = np.sqrt(egp.cov[:, i, i]) * scale[i]
        truth = test.state[1:, i] * scale[i]
        est = truth + egp.error[:, i] * scale[i]
        ax.plot(t, truth, "k", lw=1, label="truth (Vicon)")
        ax.plot(t, est, "C0", lw=1, label="EGP-EKF mean")
        ax.fill_between(t, est - 3 * sd, est + 3 * sd, color="C0", alpha=0.25, label="EGP-EKF 3 sigma")
        ax.set_ylabel(f"{names[i]} ({units[i]})")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("time in the held-out part (s)")
    fig.suptitle("MRCLAM Dataset 6, robot 1, held-out 30 %: EGP-EKF with 3-sigma bands")
    fig.tight_layout()
    fig.savefig(out / "trajectory.png", dpi=110)
    plt.close(fig)
    fig, axes = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    book_err = system.state_error(book_mean, test.state[1:])
    for ax, i, label in ((axes[0], slice(0, 2), "position error (cm)"), (axes[1], 2, "heading error (deg)")):
        f = 100 if label.startswith("position") else 180 / math.pi
        e1 = (
            np.linalg.norm(np.atleast_2d(egp.error[:, i].T).T, axis=1)
            if isinstance(i, slice)
            else np.abs(egp.error[:, i])
        )
        e2 = np.linalg.norm(book_err[:, i], axis=1) if isinstance(i, slice) else np.abs(book_err[:, i])
        ax.plot(t, e1 * f, "C0", lw=1, label="EGP-EKF")
        ax.plot(t, e2 * f, "C3", lw=1, label="textbook EKF")
        ax.set_ylabel(label)
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel("time in the held-out part (s)")
    fig.tight_layout()
    fig.savefig(out / "errors.png", dpi=110)
    plt.close(fig)
    param = load_parametric(models, system)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for k, sensor in enumerate(system.sensors):
        xs, zs = test.readings(k)
        if not len(xs):
            continue
        means = param.sensor_means["type-landmark"](
            np.concatenate([xs, np.tile(sensor.constants, (len(xs), 1))], 1)
        )
        r = zs - means
        r[:, 1] = wrap(r[:, 1])
        for j, ax in enumerate(axes):
            ax.errorbar(
                k,
                r[:, j].mean() * (1 if j == 0 else 180 / math.pi),
                yerr=r[:, j].std() * (1 if j == 0 else 180 / math.pi),
                fmt="o",
                color="C0",
            )
    for ax, label in zip(axes, ("range residual (m)", "bearing residual (deg)"), strict=True):
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xticks(range(system.n_sensors), [s.name for s in system.sensors], rotation=60, fontsize=7)
        ax.set_ylabel(label)
    fig.suptitle(
        "Held-out readings minus the fitted range-bearing model at the truth (mean +- sd per landmark)"
    )
    fig.tight_layout()
    fig.savefig(out / "landmark_residuals.png", dpi=110)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=HERE)
    p.add_argument("--quick", action="store_true", help="a small run for the smoke test")
    p.add_argument("--reuse-models", action="store_true", help="track with OUT/models of an earlier run")
    p.add_argument("--report-only", action="store_true", help="rewrite OUT/report.md from OUT/results.json")
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.report_only:
        result = json.loads((args.out / "results.json").read_text())
        result["consistency"] = consistency(result["held_out"])  # derived: kept up to date with its rule
        atomic_write_text(args.out / "results.json", json.dumps(result, indent=1) + "\n")
        atomic_write_text(args.out / "report.md", report(result))
    else:
        result = run(args.out, args.quick, args.reuse_models)
    print(json.dumps(result["summary"]))


if __name__ == "__main__":
    main()
