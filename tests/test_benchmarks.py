"""Smoke tests: every benchmark runs in --quick mode and ends with its JSON figures."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

EXPECTED = {
    "bench_agents.py": {
        "state_steps_per_s", "belief_steps_per_s", "belief_to_state_ratio", "batched_belief_to_state_ratio",
        "filter_ms", "variance_floor_ms", "ratio_at_floor",
    },
    "bench_service.py": {
        "rtt_p50_ms", "rtt_p99_ms", "overhead_p50_ms", "blimps_at_4hz", "fleet_blimps_at_4hz",
        "overhead_over_zenoh_floor", "service_cpu_per_step_over_echo", "forged_token_sessions_lost",
        "forged_token_resets_ok",
        "hung_owner_failover_s", "stale_owner_overrides", "near_horizon_healthy_p99_ms", "queue_bytes_max_mb",
    },
    "bench_filters.py": {
        "ekf_ms", "ukf_ms", "pf_exact_ms", "pf_sparse_ms",
        "speedup_ekf", "speedup_ukf", "speedup_pf_exact", "speedup_pf_sparse", "ekf_ratio_to_bw_limit",
        "pf_per_particle_spread",
    },
    "bench_env.py": {"single_env_steps_per_s", "batched64_steps_per_s", "lab_single_env_steps_per_s"},
    "bench_consistency.py": {
        "nees_ratio_min", "nees_ratio_max", "coverage2_min", "coverage2_max", "loglik_gain_min",
        "rms_change_max", "perturbed_coverage2_min", "targets_met", "within3_min", "pf_within3_min",
        "failed_runs_max",
    },
    "model_swap.py": {
        "param_ang_velocity_deg_s", "gp_pred_param_obs_ang_velocity_deg_s", "gp_yaw_rate_deg_s",
    },
    "bench_training.py": {
        "exact_nll_ms_default_threads", "exact_nll_ms_one_thread", "potri_speedup",
        "subset_fit_speedup", "subset_to_full_rms_ratio", "exact_nll_ratio_to_flop_limit",
        "train_default_s", "calibration_share",
    },
    "bench_gp.py": {
        "batch_mean_var_s", "achieved_gflops", "matmul_gflops", "speedup_vs_sklearn",
        "one_query_ms", "25_queries_ms", "ratio_to_flop_limit", "one_query_ratio_to_bw_limit",
    },
}  # fmt: skip


#: scripts whose --quick run is over a minute have a --smoke mode for this test
SMOKE = {
    "bench_agents.py",
    "bench_consistency.py",
    "bench_filters.py",
    "bench_service.py",
    "bench_training.py",
}


@pytest.mark.parametrize("script", sorted(EXPECTED))
def test_benchmark_quick_mode_prints_json_last(script: str) -> None:
    flag = "--smoke" if script in SMOKE else "--quick"
    out = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), flag],
        check=True, capture_output=True, text=True, timeout=240,
    )  # fmt: skip
    last = json.loads(out.stdout.strip().splitlines()[-1])
    assert EXPECTED[script] <= set(last)
    if script != "model_swap.py":  # every benchmark measures this machine's limits in its own run
        assert {"dgemm_gflops", "read_gbs"} <= set(last)
    assert all(isinstance(last[k], (int, float)) and math.isfinite(last[k]) for k in EXPECTED[script])
    if script == "bench_service.py":  # the hostile peer's figures, even at smoke size
        assert last["forged_token_sessions_lost"] == 0 and last["forged_token_resets_ok"] == 1.0
        assert last["stale_owner_overrides"] == 0 and last["hung_owner_failover_s"] <= 3.0
        assert last["queue_bytes_max_mb"] <= 4.0  # (the near-horizon p99 is timing: judged by the full run)


def test_the_consistency_report_opens_with_its_provenance(tmp_path: Path) -> None:
    """bench_consistency.py --out: its report's first line under the title names the code
    version, the command and the wall time, as every committed report's does."""
    out = tmp_path / "consistency" / "results.json"
    subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_consistency.py"), "--smoke", "--out", str(out)],
        check=True, capture_output=True, text=True, timeout=240,
    )  # fmt: skip
    line = (out.parent / "report.md").read_text().splitlines()[2]
    assert line.startswith("Provenance: code ") and "bench_consistency.py --smoke --out" in line, line
    assert set(json.loads(out.read_text())["provenance"]) == {"code", "command", "wall_s"}


def test_the_real_robot_experiment_runs_quick_and_reports(tmp_path: Path) -> None:
    """docs/results/real_mrclam/experiment.py --quick: the committed event logs align, the
    user's models train (with the cross-fitted calibration), every judged figure is in
    results.json and on the last line, and the report names them."""
    out = subprocess.run(
        [sys.executable, str(ROOT / "docs" / "results" / "real_mrclam" / "experiment.py"), "--quick",
         "--out", str(tmp_path)],
        check=True, capture_output=True, text=True, timeout=240,
    )  # fmt: skip
    last = json.loads(out.stdout.strip().splitlines()[-1])
    judged = {"egp_ekf_rms_ratio_to_textbook", "egp_ekf_nees_ratio", "egp_ekf_ms_per_step"}
    assert judged <= set(last) and all(math.isfinite(last[k]) for k in judged)
    result = json.loads((tmp_path / "results.json").read_text())
    assert result["quick"] and result["control_delay_s"] in (0.15, 0.2, 0.25)
    assert set(result["calibration"]) == {"param", "egp"}
    report = (tmp_path / "report.md").read_text()
    assert all(f"`{k}`" in report for k in judged) and "textbook ekf" in report
    assert report.splitlines()[2].startswith("Provenance: code ") and "experiment.py --quick" in report
    assert set(result["provenance"]) == {"code", "command", "wall_s"}


def test_the_pf_update_experiment_runs_quick_and_summarises(tmp_path: Path) -> None:
    """docs/results/pf_update/experiment.py --quick: models train, both update rules track
    every segment, and the last line holds each kind's comparison."""
    out = subprocess.run(
        [sys.executable, str(ROOT / "docs" / "results" / "pf_update" / "experiment.py"), "--quick",
         "--seed", "5", "--kinds", "param,gp", "--folds", "0", "--out", str(tmp_path)],
        check=True, capture_output=True, text=True, timeout=240,
    )  # fmt: skip
    last = json.loads(out.stdout.strip().splitlines()[-1])
    assert set(last["summary"]) == {"param", "gp"}
    for per in last["summary"].values():
        assert per["table1"]["runs"] == per["bridge"]["runs"] > 0
        assert math.isfinite(per["bridge_rms_ratio"]) and math.isfinite(per["bridge_mll_gain"])
    rows = json.loads((tmp_path / "rows.json").read_text())
    assert {r["rule"] for r in rows} == {"table1", "bridge"} and len(rows) == 2 * sum(
        p["table1"]["runs"] for p in last["summary"].values()
    )
    traced = subprocess.run(
        [sys.executable, str(ROOT / "docs" / "results" / "pf_update" / "experiment.py"), "--quick",
         "--seed", "5", "--kinds", "gp", "--out", str(tmp_path), "--trace", "0,0,5", "--rule", "bridge"],
        check=True, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    lines = traced.stdout.strip().splitlines()
    worst = json.loads(lines[-1])
    assert lines[0].startswith("step") and worst["rule"] == "bridge" and 0 < worst["ess_min"] <= 200
    assert all(math.isfinite(worst[k]) for k in ("prior_mm", "post_mm"))
