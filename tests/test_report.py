"""The report's Table 7 measure, the orderings it checks, and its hand-written notes."""

from __future__ import annotations

from pathlib import Path

import pytest

from agents.experiments.measures import aggregate_gain, improvement
from agents.experiments.report import _checks, _filter_checks
from agents.experiments.report_notes import NOTES_MARKER, write_keeping_notes
from agents.experiments.report_why import WHY


def _row(p: float, xi: float, v: float, w: float, step: float = 1.0) -> dict:
    row = {"position_mm": [p, 0.0], "orientation_deg": [xi, 0.0], "velocity_mm_s": [v, 0.0]}
    row |= {"ang_velocity_deg_s": [w, 0.0], "step_ms": [step, 0.0]}
    return row | {"aggregate_rms": [(p + xi + v + w) / 4, 0.0]}


def test_improvement_averages_the_groups_not_the_mixed_unit_sum() -> None:
    # the GP halves the position error (mm) but doubles the orientation error (deg)
    tr = {"ekf/param": _row(40.0, 1.0, 20.0, 1.0), "ekf/gp": _row(20.0, 2.0, 20.0, 1.0)}
    assert improvement(tr, "ekf/gp", "ekf/param") == pytest.approx((50.0 - 100.0) / 4)
    # the mixed-unit sum the report shows beside it calls the same rows a 29% improvement
    assert aggregate_gain(tr, "ekf/gp", "ekf/param") == pytest.approx(100 * (1 - 10.75 / 15.5))


def test_checks_use_table_7_measure_for_the_20_percent_claim() -> None:
    tr = {
        "ukf/param": _row(40.0, 1.0, 20.0, 1.0),
        "ukf/gp": _row(20.0, 1.1, 15.0, 1.1, step=10.0),  # (50 - 10 + 25 - 10) / 4 = 13.75%
        "ukf/egp": _row(16.0, 0.8, 14.0, 0.9),  # 35%
        "ukf/sparse": _row(21.0, 1.1, 15.0, 1.1, step=1.0),
    }
    verdicts = {claim.split(" (")[0]: ok for _, claim, ok in _filter_checks(tr, "ukf")}
    assert verdicts == {
        "UKF: GP improves over Param by >= 20%": False,
        "UKF: EGP at least as good as GP": True,
        "UKF: sparse within 10% of exact GP RMS and >= 5x faster": True,
    }
    tr["ukf/gp"] = _row(20.0, 0.9, 15.0, 0.9, step=10.0)  # (50 + 10 + 25 + 10) / 4 = 23.75%
    assert _filter_checks(tr, "ukf")[0][2]


def test_hetgp_is_not_best_when_the_parametric_filter_beats_every_gp() -> None:
    tr = {
        "pf/param": _row(20.0, 1.0, 20.0, 1.0),
        "pf/gp": _row(40.0, 2.0, 40.0, 2.0),  # -100%
        "pf/hetgp": _row(24.0, 1.2, 24.0, 1.2),  # -20%, best of the GPs
    }
    verdicts = {claim.split(" (")[0]: ok for _, claim, ok in _filter_checks(tr, "pf")}
    assert verdicts["PF: hetGP best or tied"] is False


def test_ukf_against_ekf_averages_the_groups_and_failed_claims_get_their_explanation() -> None:
    # the UKF is 10% worse on both angles and 1% better on the mm groups: the mm-dominated
    # aggregate RMS favours it, Table 7's group average does not
    tr = {"ekf/gp": _row(20.0, 1.0, 20.0, 1.0), "ukf/gp": _row(19.8, 1.1, 19.8, 1.1)}
    lines = _checks({"tracking": tr, "table5_6": {}})
    row = next(line for line in lines if "GP-UKF edges out GP-EKF" in line)
    assert row.endswith("| **no** |")
    explanation = dict(WHY)["GP-UKF edges out"]
    assert f"- {explanation}" in lines


def test_a_regenerated_report_keeps_its_hand_written_notes_once(tmp_path: Path) -> None:
    path = tmp_path / "report.md"
    write_keeping_notes(path, ["# Report", "", "| a | 1 |"])
    assert path.read_text() == "# Report\n\n| a | 1 |\n"
    notes = f"{NOTES_MARKER}\n## Reading the table\n\nthe measured cause\n"
    path.write_text(path.read_text() + "\n" + notes)
    write_keeping_notes(path, ["# Report", "", "| a | 2 |", ""])
    text = path.read_text()
    assert text == "# Report\n\n| a | 2 |\n\n" + notes
    write_keeping_notes(path, ["# Report", "", "| a | 2 |"])
    assert path.read_text() == text  # idempotent: the notes are not repeated
    path.write_text("# Report\n\n| a | 1 |\n\nno marker: generated text only\n")
    write_keeping_notes(path, ["# Report"])
    assert path.read_text() == "# Report\n"
