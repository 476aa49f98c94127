"""Pilots, flight recording, training and tracking, and the gpbf CLI end to end."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from agents.cli import main as gpbf
from agents.pilots import make_pilot
from agents.sim import collect_flight
from estimator_service.factory import load_models
from estimator_service.flight import load_flight, save_flight
from estimator_service.gp import CircularGP, EnhancedGP
from estimator_service.models.calibration import (
    NoiseScaledObservation,
    NoiseScaledPrediction,
    read_noise_scales,
)
from estimator_service.training import TrainSettings, train_models


@pytest.fixture(scope="module")
def flight():
    return collect_flight(90, seed=3)


def test_scripted_pilot_flies_five_minutes_without_crashing_and_uses_full_fan_range() -> None:
    env = gym.make("gpbf_env/Blimp-v0", max_episode_steps=10**9)
    _, info = env.reset(seed=7)
    pilot = make_pilot("scripted", np.random.default_rng(7))
    actions = []
    for _ in range(5 * 60 * 4):
        a = pilot.act(info["state"])
        actions.append(a)
        _, _, terminated, _, info = env.step(a)
        assert not terminated
    a = np.array(actions)
    assert a[:, 0].min() < -0.5 and a[:, 0].max() > 0.9  # reverse and full forward thrust
    assert a[:, 1].min() < -0.5 and a[:, 1].max() > 0.5  # vector angle both ways
    assert a[:, 2].min() < -0.5 and a[:, 2].max() > 0.5  # turns both ways


def test_collect_is_seeded_and_round_trips(flight, tmp_path: Path) -> None:
    again = collect_flight(90, seed=3)
    np.testing.assert_array_equal(flight.state, again.state)
    np.testing.assert_array_equal(flight.z, again.z)
    path = save_flight(flight, tmp_path / "f.npz")
    back = load_flight(path)
    for name in ("t", "state", "control", "z", "valid", "episode"):
        np.testing.assert_array_equal(getattr(back, name), getattr(flight, name))
    assert back.metadata["pilot"] == "scripted" and len(back.metadata["cameras"]) == 2
    assert not list(tmp_path.glob("*.tmp"))


def test_transitions_never_cross_episodes(flight) -> None:
    ep = flight.episode.copy()
    ep[100:] += 1  # pretend a crash after row 99
    f = type(flight)(flight.t, flight.state, flight.control, flight.z, flight.valid, ep, flight.metadata)
    rows = f.transition_rows()
    assert 99 not in rows and 98 in rows and 100 in rows
    _, _, xn = f.transitions()
    np.testing.assert_array_equal(xn, flight.state[rows + 1])


def test_malformed_flight_files_are_rejected(flight, tmp_path: Path) -> None:
    good = save_flight(flight, tmp_path / "good.npz")
    trunc = tmp_path / "trunc.npz"
    trunc.write_bytes(good.read_bytes()[:1000])
    with pytest.raises(ValueError, match="truncated"):
        load_flight(trunc)
    data = dict(np.load(good, allow_pickle=False))
    data["state"] = data["state"][:, :11]
    np.savez(tmp_path / "bad.npz", **data)
    with pytest.raises(ValueError, match="'state'"):
        load_flight(tmp_path / "bad.npz")


def test_a_kinds_models_do_not_depend_on_the_other_kinds_trained(flight, tmp_path: Path) -> None:
    s = TrainSettings(n_points=40, restarts=1, max_iter=3, sparse_iter=3, n_pseudo=5, calibration_seconds=0)
    train_models([flight], tmp_path / "a", kinds=["gp"], settings=s, seed=5)
    train_models([flight], tmp_path / "b", kinds=["sparse", "gp"], settings=s, seed=5)
    train_models([flight], tmp_path / "c", kinds=["gp"], settings=s, seed=6)
    for name in ("prediction_gp.npz", "observation_gp_cam0.npz"):
        with np.load(tmp_path / "a" / name) as a, np.load(tmp_path / "b" / name) as b:
            assert a.files == b.files
            for k in a.files:
                np.testing.assert_array_equal(a[k], b[k], err_msg=f"{name}:{k}")
    gp_a, gp_c = (tmp_path / d / "prediction_gp.npz" for d in "ac")
    with np.load(gp_a) as a, np.load(gp_c) as c:  # another seed: other subsets, other model
        assert any(not np.array_equal(a[k], c[k]) for k in a.files if a[k].dtype.kind == "f")


def test_cli_collect_train_track(tmp_path: Path, capsys) -> None:
    f, m, png = tmp_path / "f.npz", tmp_path / "models", tmp_path / "track.png"
    assert gpbf(["collect", "--minutes", "1.5", "--seed", "2", "--out", str(f), "--quiet"]) == 0
    args = [
        "train",
        str(f),
        "--out",
        str(m),
        "--points",
        "80",
        "--pseudo",
        "8",
        "--restarts",
        "1",
        "--max-iter",
        "8",
        "--hetero-iterations",
        "1",
        "--calibration-seconds",
        "20",
        "--calibration-folds",
        "2",
        "--calibration-condition-only",  # the refitted folds are tested in test_calibration.py
        "--kinds",
        "gp,egp,hetgp,sparse",
        "--quiet",
    ]
    assert gpbf(args) == 0
    assert sorted(p.name for p in m.glob("*.npz"))[:3] == [
        "observation_egp_cam0.npz",
        "observation_egp_cam1.npz",
        "observation_gp_cam0.npz",
    ]
    kinds = {k: load_models(m, k) for k in ("gp", "hetgp", "sparse")}
    scales = read_noise_scales(m)  # every kind got a process-noise scale from the flight
    assert set(scales) == {"param", "gp", "egp", "hetgp", "sparse"}
    pred = {k: v[0] for k, v in kinds.items()}
    for p in pred.values():  # per-output process scales: never all exactly 1
        assert isinstance(p, NoiseScaledPrediction)
    gps = {k: getattr(p, "inner", p).gp for k, p in pred.items()}
    assert isinstance(gps["hetgp"], EnhancedGP)  # hetGP models the parametric residual
    assert isinstance(gps["gp"], CircularGP) and isinstance(gps["sparse"], CircularGP)
    obs = kinds["gp"][1]  # every kind got per-output observation-noise scales, none below 1
    assert isinstance(obs, NoiseScaledObservation) and obs.scale.shape == (10,) and obs.scale.min() >= 1
    folds = json.loads((m / "calibration.json").read_text())["details"]["fold_details"]
    assert len(folds) == 2 and all(0 < max(f["observation_frames"]) <= 80 for f in folds)  # 20 s blocks
    assert obs.inner.parts[0].gp.angle_output == 4  # the ellipse orientation is circular
    capsys.readouterr()
    assert (
        gpbf(
            [
                "track",
                str(f),
                "--models",
                str(m),
                "--filter",
                "ukf",
                "--model",
                "egp",
                "--plot",
                str(png),
                "--quiet",
            ]
        )
        == 0
    )
    scores = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert scores["position_mm"] < 200 and np.isfinite(scores["mll"])
    assert png.stat().st_size > 10_000
    assert png.with_name(f"{png.stem}_normalised.png").stat().st_size > 10_000  # error / sd per group
    assert png.with_name(f"{png.stem}_reliability.png").stat().st_size > 10_000  # nominal vs observed
    assert gpbf(["track", str(tmp_path / "missing.npz"), "--models", str(m), "--quiet"]) == 2


def _no_training(*args: object, **kwargs: object) -> None:
    raise AssertionError("a resumed run trained or tracked again")


def test_reproduce_runs_end_to_end_on_tiny_sizes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from dataclasses import replace

    from agents.experiments.reproduce import ReproduceSettings, reproduce, split_folds

    s = ReproduceSettings(
        minutes=1.5,
        folds=2,
        points=40,
        pseudo=8,
        max_iter=5,
        track_seconds=20,
        particles=50,
        kinds=("param", "gp", "egp", "sparse"),
        landmark=False,
        pf_seconds=5,
        fig3_repeats=1,
        fig3_smallest=20,
        fig3_pseudo=(4,),
        calibration_folds=2,
        calibration_refit=False,  # the refitted folds are tested in test_calibration.py
    )
    res = reproduce(tmp_path, s, progress=False, jobs=2)  # units in worker processes
    report = (tmp_path / "report.md").read_text()
    for heading in ("Table 5", "Table 6", "Tables 7-9", "Fig. 3", "Fig. 4", "The paper's results, checked"):
        assert heading in report
    assert set(res["tracking"]) == {f"{f}/{k}" for f in ("ukf", "ekf", "pf") for k in s.kinds}
    assert res["tracking"]["pf/gp"]["steps"] == [20, 0] and res["tracking"]["ekf/gp"]["steps"] == [80, 0]
    assert set(res["fig3"]["points"]) == {"20", "40"} and set(res["fig3"]["pseudo"]) == {"4"}
    fig3 = res["fig3"]["points"]["40"]["ukf"]
    assert 0 <= fig3["outside_3sigma"][0] <= 1 and np.isfinite(fig3["aggregate_rms"][0])
    assert (tmp_path / "fig4_left_turns.png").exists() and (tmp_path / "fig3_training_points.png").exists()
    train, test = split_folds(collect_flight(20, seed=0), 2)[1]
    assert len(train.transition_rows()) == len(train) - 1 and len(test) == 40
    assert set(res["claims"]) >= {"table5_gp_beats_param", "table7_ekf_gp_20pct"}
    assert all(isinstance(v, bool) for v in res["claims"].values())
    assert set(res["beyond"]) <= {"table7_pf_hetgp_best", "table10_ukf_worst_toolbox"}
    for g in ("position_mm", "velocity_mm_s"):  # the paper's mean norm beside RMS, exact-state scores
        assert 0 < res["table5_6"]["gp"][f"norm_{g}"][0] and 0 < res["tracking"]["ekf/gp"][f"exact_{g}"][0]
    assert "Mean error norm" in report and "against the exact state" in report
    import agents.experiments.fig3 as fig3_module
    import agents.experiments.reproduce as reproduce_module

    monkeypatch.setattr(reproduce_module, "train_models", _no_training)
    monkeypatch.setattr(reproduce_module, "tracking", _no_training)  # the folds' scores are kept too
    monkeypatch.setattr(fig3_module, "train_models", _no_training)
    again = reproduce(tmp_path, s, progress=False)  # resumes: nothing trained again, the same tables
    untimed = lambda r: {k: {m: v for m, v in d.items() if m != "step_ms"} for k, d in r["tracking"].items()}  # noqa: E731
    assert untimed(again) == untimed(res) and again["fig3"] == res["fig3"]
    with pytest.raises(ValueError, match=r"other settings \(points\)"):
        reproduce(tmp_path, replace(s, points=41), progress=False)
    (tmp_path / "settings.json").unlink()  # models from a run that kept no record: not adopted
    with pytest.raises(ValueError, match="recorded no settings"):
        reproduce(tmp_path, s, progress=False)


def test_gap_sweep_runs_on_tiny_sizes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import agents.experiments.gap_sweep as gap_module
    from agents.experiments.gap_report import SWEEP_FOLDER, report_lines
    from agents.experiments.gap_sweep import gap_sweep
    from agents.experiments.reproduce import ReproduceSettings

    assert report_lines(tmp_path) == []  # a reproduction's report without a sweep has no section
    run, tmp_path = tmp_path, tmp_path / SWEEP_FOLDER  # where the report looks for it
    s = ReproduceSettings(minutes=1.0, folds=2, points=30, pseudo=5, max_iter=3, track_seconds=20,
                          calibration_folds=2, calibration_refit=False)  # fmt: skip
    res = gap_sweep(tmp_path, s, strengths=(0.0, 1.0), progress=False, jobs=2)
    assert set(res["improvement_pct"]) == {"0", "1"}
    assert set(res["improvement_pct"]["1"]) == {"ekf/gp", "ekf/egp", "ukf/gp", "ukf/egp"}
    assert all(np.isfinite(v) for row in res["improvement_pct"].values() for v in row.values())
    assert (tmp_path / "gap_sweep.png").stat().st_size > 5_000 and "| 1 |" in (
        tmp_path / "gap_sweep.md"
    ).read_text()
    section = "\n".join(report_lines(run))
    assert "| 1 |" in section and f"({SWEEP_FOLDER}/gap_sweep.png)" in section
    assert (
        section.count("Provenance: code ") == 1
        and "Provenance: code " in (tmp_path / "gap_sweep.md").read_text()
    )
    monkeypatch.setattr(gap_module, "train_models", _no_training)  # resumes: the same table
    monkeypatch.setattr(gap_module, "tracking", _no_training)
    again = gap_sweep(tmp_path, s, strengths=(0.0, 1.0), progress=False)
    assert again.pop("provenance")["wall_s"] < res.pop("provenance")["wall_s"] and again == res
    with pytest.raises(ValueError, match=r"other settings \(strengths\)"):
        gap_sweep(tmp_path, s, strengths=(0.0, 2.0), progress=False)


def test_landmark_experiment_tracks_with_all_filters() -> None:
    from agents.experiments.landmark import run_landmark_experiment

    for kernel in ("ard", "toolbox"):
        res = run_landmark_experiment(n_test=1, steps=60, particles=100, kernel=kernel)
        spread = res.pop("spread")
        assert set(res) == {"GP-UKF (alpha=1e-3)", "GP-UKF (alpha=1)", "GP-EKF", "GP-PF"}
        assert all(np.isfinite(v["position"]) for v in res.values()) and res["GP-EKF"]["position"] < 2.0
        assert all(v > 0 for v in spread.values())
    # ARD: the prediction GP is nearly linear in position, so alpha = 1e-3 (sigma points
    # within 0.002 sigma, the EKF plus the curvature term) equals the EKF to 2 %
    res = run_landmark_experiment(n_test=1, steps=60, particles=100)
    assert res["GP-UKF (alpha=1e-3)"]["position"] == pytest.approx(res["GP-EKF"]["position"], rel=0.02)


def test_toolbox_gp_shares_one_length_scale_and_fits_a_smooth_function() -> None:
    from agents.experiments.toolbox_gp import fit_isotropic

    rng = np.random.default_rng(0)
    x = rng.uniform(-3, 3, (80, 2))
    y = np.sin(x[:, :1]) + 0.5 * x[:, 1:] + 3.0 + 0.01 * rng.standard_normal((80, 1))
    gp = fit_isotropic(x, y, rng)
    ell = np.exp(gp.theta[0, :2])
    assert ell[0] == ell[1]
    test = rng.uniform(-2, 2, (50, 2))
    want = np.sin(test[:, :1]) + 0.5 * test[:, 1:] + 3.0
    assert np.max(np.abs(gp.predict(test).mean - want)) < 0.05


def test_persistence_finds_an_ar1_errors_mean_and_correlation() -> None:
    from agents.experiments.reproduce import persistence

    rng = np.random.default_rng(0)
    e = np.zeros(20_000)
    for k in range(1, e.size):  # AR(1), coefficient 0.9, around a mean of 1
        e[k] = 0.9 * e[k - 1] + rng.standard_normal()
    e += 1.0
    mask = np.ones(e.size, bool)
    mask[5000:5100] = False  # a gap: no pair spans it
    rms, mean, lag1 = persistence(e, mask)
    assert lag1 == pytest.approx(0.9, abs=0.02) and mean == pytest.approx(1.0, abs=0.3)
    assert rms == pytest.approx(np.sqrt(np.mean(e[mask] ** 2)))
    assert np.isnan(persistence(e, np.arange(e.size) % 2 == 0)[2])  # no consecutive rows


def test_fig4_yaw_rate_figures_use_the_tracked_episode_only() -> None:
    """The Fig. 4 filter tracks the test flight's first episode; the one-step figures must
    use the same transitions. A test flight with a second episode (a crash and reset, as
    the lab seed-1 run's had) raised an IndexError before."""
    import dataclasses
    from types import SimpleNamespace

    from agents.experiments.reproduce import _yaw_rate_figures
    from estimator_service.tracking import TrackResult

    flight = collect_flight(30, seed=1)
    first = 50
    two = dataclasses.replace(flight, episode=(np.arange(len(flight)) >= first).astype(np.int64))
    steps = first - 1
    truth = two.state[1:first]
    r = TrackResult(truth, np.repeat(np.eye(12)[None], steps, axis=0), truth, np.zeros(steps),
                    np.zeros(steps, np.int64), np.zeros(steps, bool), 0.0)  # fmt: skip
    zero = SimpleNamespace(predict=lambda x, u: SimpleNamespace(mean=np.zeros_like(x), var=np.ones_like(x)))
    left = np.arange(steps) % 2 == 0
    out = _yaw_rate_figures("m", zero, two, r, left)
    change = two.system.state_error(two.state[1:first], two.state[: first - 1])[left, 11]
    want = float(np.degrees(np.sqrt(np.mean(change**2))))
    assert out["m: one-step yaw-rate change error in left turns (deg/s)"] == pytest.approx(want)
    assert out["m: yaw-rate error in left turns (deg/s)"] == 0.0
