"""Markdown report of ``gpbf reproduce`` results, with the paper's orderings checked."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from agents.tracking import GROUPS, consistency_band
from estimator_service.gp.io import atomic_write_text
from estimator_service.models.calibration import read_noise_scales, read_observation_scales

__all__ = ["write_report"]

# Why a claim can fail on this simulator; shown under the table for each claim that fails.
WHY = (
    (
        "GP beats Param",
        "The parametric model here has the simulator's own structure (rigid body, fan thrust, "
        "drag) with fitted coefficients; the paper's parametric model missed real aerodynamics. "
        "Its one-step error is set by the fans' first-order lag (time constants 0.2-0.35 s "
        "against 0.25 s steps), which no model of (x_k, u_k) can see: on a 5-minute test "
        "flight the parametric position error was 1.12 mm, 1.15 mm without gusts and 0.36 mm "
        "with near-instant fans (0.02 s). A zero-mean GP must learn the body-to-world rotation "
        "of the velocity from ~900 points in a 16-D input space and loses on position either "
        "way (1.74 vs 1.12 mm with the simulator's fans, 1.30 vs 0.36 mm with instant ones, 15 "
        "minutes of training flight); the EGP, which starts from the parametric model, is the "
        "fair test of what the GP adds.",
    ),
    (
        "EGP beats Param",
        "The EGP's margin over a parametric model at the noise floor is a few percent, within "
        "the fold-to-fold spread on some groups.",
    ),
    (
        "sparse within 10%",
        "Fifty pseudo-inputs cover a 16-D input space thinly: on the first fold the sparse "
        "model's one-step position error was 1.85 vs 1.43 mm and its ellipse-angle error "
        "8 vs 3.3 deg. More optimiser iterations raised the marginal likelihood but not the "
        "tracking (aggregate RMS 14.6, 12.3, 13.2, 13.3 after 60, 120, 200, 500 iterations), "
        "the effect the paper itself reports for larger pseudo-input sets.",
    ),
    (
        "GP improves aggregate RMS",
        "A zero-mean GP needs data wherever the filter goes: with few training points (the "
        "quick run's 150 from a 4-minute flight) it reverts to its prior between them, where "
        "the EGP falls back on the parametric model. At paper size the outcome also depends on "
        "the training draws (which points, which hyperparameter subsets): in the full run "
        "before this one, which differed only in its random streams, the GP-EKF lost track "
        "on one of the eight test segments (aggregate RMS 88.7; the other seven 9.3-16.3) "
        "and scored -8% against 41% here. That fold's prediction GP lost the segment at "
        "every process-noise scale from 1.5 to 4.5.",
    ),
    (
        "PF:",
        "Calibrating the observation noise on held-out frames stopped the exact-GP particle "
        "filters from failing outright: without it their aggregate RMS was 87.5 (GP), 59.0 "
        "(EGP), 42.0 (hetGP) and 14.0 (sparse) against the parametric PF's 15.7. They still "
        "lost segments: a camera frame could leave one particle with nearly all the weight "
        "(effective sample size about 1), and roughening with the weighted cloud's covariance "
        "then shrank the cloud to a 3 mm position spread while its error grew to 0.7 m (seed-0 "
        "run, fold 0, first segment). The PF now roughens with the Kalman-updated covariance "
        "of the predicted cloud, which one heavy particle cannot collapse; on the seed-0 "
        "run's models this took the aggregate RMS from 24.9 to 13.3 (GP), 20.7 to 10.4 (EGP), "
        "27.2 to 9.9 (hetGP), 15.3 to 11.8 (sparse) and 17.0 to 16.2 (Param). What keeps the "
        "GP-PF under 20% there is mostly one segment (22.0; the other seven 10.8-13.2). On "
        "the seed-1 run's models the same change gave 22.4 (GP), 15.0 (EGP), 15.5 (hetGP), "
        "14.5 (sparse) and 20.6 (Param): the plain GP-PF still trails there. The "
        "roughening factor (1.0) was not tuned on test segments, and an exact-GP PF step "
        "costs 0.17-0.21 s at 500 particles, so more particles were not tried.",
    ),
    (
        "Table 10",
        "Our landmark GPs learn long length scales exactly along the directions in which the "
        "sigma points leave the training band: eq. (31)-(32) do not depend on position (learned "
        "position length scales ~4,000 units) and the range GPs are smooth (10-15 units "
        "against a sigma-point spread below 1 unit), so off-path sigma points still get "
        "accurate predictions. In a sweep (landmarks 1.4 units from the corners or 0.5 units "
        "from the sides, range noise 0.05 and 0.2, process noise x1 and x4, initial standard "
        "deviation 0.5) the GP-UKF's position RMS was 0.05 to 1.00 times the GP-EKF's; "
        "initial standard deviations up to 2 with the default layout changed nothing.",
    ),
    (
        "Fig. 4: the truth stays",
        "The GP-UKF's yaw variance grows where the left-turn data were removed, but not "
        "enough to cover every larger error. Left turns share every input but the tail "
        "command with the rest of the flight, and the GP extrapolates from right turns and "
        "straight flight with a long length scale on that input. Across full runs the truth "
        "stayed within 3 sigma on 72-97% of those steps (95% is asked), and on 93-98% of "
        "all steps with all data.",
    ),
    (
        "Fig. 4: without left-turn data",
        "How much the yaw variance grows in left turns depends on the training draws: x1.64, "
        "x1.24 and x1.13 in three full runs (x1.2 is asked), against x0.92-1.22 elsewhere. "
        "The GP can explain the yaw-rate change with inputs other than the tail command.",
    ),
    (
        "GP-UKF edges out",
        "GP-UKF and GP-EKF are within 1% of each other here, well inside the fold-to-fold "
        "spread (about 2.4); the UKF was ahead in the two full runs before this one.",
    ),
    (
        "hetGP best",
        "The simulator's process noise (wind gusts) does not depend on the state, so a "
        "heteroscedastic model has little to gain over the EGP it builds on.",
    ),
)

PAPER_T5 = {"param": (3.3, 0.5, 14.6, 1.5), "gp": (1.8, 0.2, 9.8, 1.1), "egp": (1.6, 0.2, 9.6, 1.3)}


def _big(x: float, fmt: str = "{:.1f}") -> str:
    """``fmt``, or powers of ten for the astronomic values of a collapsed particle cloud."""
    return f"{x:.1e}" if abs(x) >= 1e5 else fmt.format(x)


def _ms(v: list[float], fmt: str = "{:.2f}") -> str:
    return f"{fmt.format(v[0])} ± {fmt.format(v[1])}"


def _table5(res: dict) -> list[str]:
    t = res["table5_6"]
    lines = [
        "## Table 5: one-step prediction error (RMS; paper units)",
        "",
        "| model | p (mm) | ξ (deg) | v (mm/s) | ω (deg/s) | paper (p, ξ, v, ω) |",
        "| --- | ---: | ---: | ---: | ---: | --- |",
    ]
    for k, v in t.items():
        cells = " | ".join(_ms(v[g]) for g in GROUPS)
        lines.append(f"| {k} | {cells} | {PAPER_T5.get(k, '')} |")
    lines += [
        "",
        "## Table 6: observation error (RMS over valid frames)",
        "",
        "| model | ellipse position (px) | width/height (px) | angle (deg) |",
        "| --- | ---: | ---: | ---: |",
    ]
    for k, v in t.items():
        lines.append(
            f"| {k} | {_ms(v['ellipse_position_px'])} | {_ms(v['ellipse_size_px'])} | "
            f"{_ms(v['ellipse_angle_deg'])} |"
        )
    return [*lines, ""]


def _tables7_9(res: dict) -> list[str]:
    tr = res["tracking"]
    filters = sorted({k.split("/")[0] for k in tr}, key=("ukf", "ekf", "pf").index)
    kinds = [k for k in ("param", "gp", "egp", "hetgp", "sparse") if f"{filters[0]}/{k}" in tr]
    lines = [
        "## Tables 7-9: tracking (held-out folds)",
        "",
        "Aggregate RMS = mean of the four group RMS values (mm, deg, mm/s, deg/s). Improvement is "
        "relative to the same filter with the parametric models. MLL = mean log-likelihood of "
        "the true state. NEES/NIS: time averages (consistent: NEES ≈ 12, NIS/dof ≈ 1). "
        "Uncalibrated, every filter, the parametric ones included, is overconfident: the "
        "simulated wind gusts are an Ornstein-Uhlenbeck process with a 3 s correlation time, an "
        "unobserved state that the filters treat as white process noise, so errors persist "
        "over many steps. Each model kind's prediction noise is therefore scaled by the "
        "factor that brings the EKF's NEES nearest 12 on the first minute of the training "
        "flight (scales below). That minute's camera frames are kept out of the observation "
        "models, and each observation output's variance is scaled by its mean squared "
        "standardised residual there (at least 1): a GP's variance is smallest on its own "
        "training frames, and a too-narrow likelihood leaves a particle filter with a handful "
        "of particles. On held-out data the GP filters stay somewhat overconfident for the same "
        "reason. A run counts as failed when the truth is outside the 3-sigma ellipsoid on "
        "more than 10% of its steps.",
        "",
        "| filter | model | aggregate RMS | improvement | MLL | step (ms) | NEES | NIS/dof | failed runs |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for f in filters:
        base = tr[f"{f}/param"]["aggregate_rms"][0] if f"{f}/param" in tr else float("nan")
        for k in kinds:
            v = tr[f"{f}/{k}"]
            imp = 100 * (1 - v["aggregate_rms"][0] / base)
            lines.append(
                f"| {f.upper()} | {k} | {_ms(v['aggregate_rms'])} | {imp:.0f}% | {_big(v['mll'][0])} | "
                f"{v['step_ms'][0]:.2f} | {_big(v['nees'][0])} | {_big(v['nis_per_dof'][0], '{:.2f}')} | "
                f"{v['failed'][0]:.2f} |"
            )
    return [*lines, "", *_bands(res), *_scales_line(res)]


def _bands(res: dict) -> list[str]:
    """The 95% bands of a consistent filter's averaged NEES and NIS/dof, and who is inside."""
    tr, folds = res["tracking"], res["settings"]["folds"]
    parts, inside = [], []
    for key, v in tr.items():
        if "nees_var" not in v:
            return []
        f, k = key.split("/")
        nees = consistency_band(12.0, v["nees_var"][0] / folds)
        nis = consistency_band(1.0, v["nis_var"][0] / folds)
        if k == "param":
            parts.append(f"{f.upper()} NEES {nees[0]:.2f}-{nees[1]:.2f}, NIS/dof {nis[0]:.3f}-{nis[1]:.3f}")
        for name, val, band in (("NEES", v["nees"][0], nees), ("NIS", v["nis_per_dof"][0], nis)):
            if band[0] <= val <= band[1]:
                inside.append(f"{f.upper()}-{k} {name}")
    return [
        "95% bands of a consistent filter for these averages (normal approximation to their "
        f"chi-square laws, steps taken as independent): {'; '.join(parts)}. "
        f"Inside their band: {', '.join(inside) if inside else 'none'}.",
        "",
    ]


def _kinds(per_fold: list[dict]) -> list[str]:
    return sorted({k for f in per_fold for k in f}, key=lambda k: (k != "param", k))


def _scales_line(res: dict) -> list[str]:
    lines = []
    scales = res.get("noise_scales") or []
    if scales:
        nan = float("nan")
        cells = ", ".join(k + " " + "/".join(f"{f.get(k, nan):g}" for f in scales) for k in _kinds(scales))
        lines += [f"Process-noise scales per fold: {cells}.", ""]
    obs = res.get("observation_scales") or []
    if any(obs):
        pooled = {k: np.concatenate([np.ravel(f[k]) for f in obs if k in f]) for k in _kinds(obs)}
        cells = ", ".join(f"{k} {np.median(v):.2g}/{np.max(v):.2g}" for k, v in pooled.items())
        lines += [f"Observation-noise scales (median/largest over outputs and folds): {cells}.", ""]
    return lines


def _checks(res: dict) -> list[str]:
    tr, t5 = res["tracking"], res["table5_6"]
    checks = []
    if "param" in t5:
        for k in ("gp", "egp"):
            if k in t5:
                ok = all(t5[k][g][0] < t5["param"][g][0] for g in GROUPS)
                checks.append((f"{k.upper()} beats Param in one-step prediction on every state group", ok))
    for f in sorted({k.split("/")[0] for k in tr}):
        rms = {k.split("/")[1]: v["aggregate_rms"][0] for k, v in tr.items() if k.startswith(f + "/")}
        if "param" in rms and "gp" in rms:
            checks.append(
                (
                    f"{f.upper()}: GP improves aggregate RMS over Param by >= 20% "
                    f"({100 * (1 - rms['gp'] / rms['param']):.0f}%)",
                    rms["gp"] <= 0.8 * rms["param"],
                )
            )
        if "egp" in rms and "gp" in rms:
            checks.append((f"{f.upper()}: EGP at least as good as GP", rms["egp"] <= rms["gp"] * 1.02))
        if "hetgp" in rms:
            checks.append((f"{f.upper()}: hetGP best or tied", rms["hetgp"] <= min(rms.values()) * 1.05))
        if "sparse" in rms and "gp" in rms:
            sp = tr[f"{f}/sparse"]["step_ms"][0]
            ex = tr[f"{f}/gp"]["step_ms"][0]
            checks.append(
                (
                    f"{f.upper()}: sparse within 10% of exact GP RMS and >= 5x faster "
                    f"({rms['sparse'] / rms['gp']:.2f}x RMS, {ex / sp:.1f}x speed)",
                    rms["sparse"] <= 1.1 * rms["gp"] and ex >= 5 * sp,
                )
            )
    if "ukf/gp" in tr and "ekf/gp" in tr:
        checks.append(
            ("GP-UKF edges out GP-EKF", tr["ukf/gp"]["aggregate_rms"][0] <= tr["ekf/gp"]["aggregate_rms"][0])
        )
    f4 = res.get("fig4", {})
    if "no left turns: yaw std in left turns (deg)" in f4:
        grow = f4["no left turns: yaw std in left turns (deg)"] / f4["full data: yaw std in left turns (deg)"]
        rest = f4["no left turns: yaw std elsewhere (deg)"] / f4["full data: yaw std elsewhere (deg)"]
        checks.append(
            (
                f"Fig. 4: without left-turn data the yaw uncertainty grows in left turns "
                f"(x{grow:.2f}) more than elsewhere (x{rest:.2f})",
                grow > 1.2 and grow > rest,
            )
        )
        inside = f4.get("no left turns: truth within 3 sigma in left turns", float("nan"))
        checks.append(
            (
                f"Fig. 4: the truth stays within 3 sigma in those left turns ({100 * inside:.0f}% of steps)",
                inside >= 0.95,
            )
        )
    t10 = res.get("table10", {})
    if t10:
        ukf = t10.get("GP-UKF (alpha=1)", {}).get("position", float("nan"))
        checks.append(
            (
                "Table 10: GP-UKF tracks worse than GP-EKF and GP-PF",
                ukf > t10["GP-EKF"]["position"] and ukf > t10["GP-PF"]["position"],
            )
        )
    lines = ["## The paper's orderings, checked", "", "| claim | holds here |", "| --- | --- |"]
    lines += [f"| {c} | {'yes' if ok else '**no**'} |" for c, ok in checks]
    return [*lines, "", *_why([c for c, ok in checks if not ok])]


def _why(failed: list[str]) -> list[str]:
    """One explanation per kind of failed claim."""
    notes = [text for key, text in WHY if any(c.startswith(key) or f": {key}" in c for c in failed)]
    if not notes:
        return []
    return ["### Where our numbers differ, and why", "", *[f"- {t}" for t in notes], ""]


def write_report(out: Path, res: dict) -> Path:
    s = res["settings"]
    folders = sorted(out.glob("models_fold*"), key=lambda p: int(p.name.removeprefix("models_fold")))
    if "noise_scales" not in res:  # read them from the model folders when still there
        res = {**res, "noise_scales": [read_noise_scales(f) for f in folders]}
    if "observation_scales" not in res:
        res = {**res, "observation_scales": [read_observation_scales(f) for f in folders]}
    lines = [
        "# GP-BayesFilters reproduced on the simulated blimp",
        "",
        f"{s['minutes']:.0f} minutes of scripted flight, {s['folds']}-fold cross-validation over contiguous "
        f"blocks, {s['points']} GP training points, {s['pseudo']} pseudo-inputs, PF with {s['particles']} "
        f"particles (first {s.get('pf_seconds', s['track_seconds']):.0f} s of each segment), tracking "
        f"segments of {s['track_seconds']:.0f} s. Raw numbers: `results.json`."
        + (f" The whole run took {res['wall_s'] / 60:.1f} minutes." if "wall_s" in res else ""),
        "",
    ]
    lines += _table5(res) + _tables7_9(res)
    if res.get("fig3"):
        from agents.fig3 import describe

        lines += [
            "## Fig. 3: tracking against the amount of training data (first fold)",
            "",
            "Random subsets of the training points for exact GPs (dashed) and sparse GPs with "
            "that many pseudo-inputs trained on all points (solid); means over repeats and "
            "tracking segments.",
            "",
            "![fig3](fig3_training_points.png)",
            "",
            *describe(res["fig3"]),
            "",
        ]
    lines += [
        "## Fig. 4: no training data with the tail fan pushing left",
        "",
        "![fig4](fig4_left_turns.png)",
        "",
    ]
    lines += [f"- {k}: {v:.3f}" for k, v in res["fig4"].items()] + [""]
    if res.get("table10"):
        lines += [
            "## Table 10: synthetic landmark robot (position and velocity RMS)",
            "",
            "| filter | position | velocity | step (ms) |",
            "| --- | ---: | ---: | ---: |",
        ]
        for k, v in res["table10"].items():
            lines.append(
                f"| {k} | {v['position']:.3f} ± {v['position_se']:.3f} | "
                f"{v['velocity']:.3f} ± {v['velocity_se']:.3f} | {v['step_ms']:.2f} |"
            )
        lines.append("")
    lines += _checks(res)
    path = out / "report.md"
    atomic_write_text(path, "\n".join(lines))
    return path
