"""Belief wrappers, both back ends, and stable-baselines3 training on beliefs."""

from __future__ import annotations

import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

from agents.rl import AgentSpec, evaluate_agent, load_agent, make_vec, train_agent
from agents.rl.wrappers import INIT_STD, VARIANTS, make_belief_env
from agents.sim import collect_flight
from estimator_service.factory import build_filter
from estimator_service.filters import GaussianBelief
from estimator_service.service.client import free_port, open_session
from estimator_service.training import TrainSettings, train_models


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> str:
    out = tmp_path_factory.mktemp("rl_models")
    flight = collect_flight(60, seed=4)
    train_models(
        [flight],
        out,
        kinds=["param", "gp"],
        settings=TrainSettings(  # calibration is not the subject here (refitted folds: test_calibration)
            n_points=60, n_pseudo=8, restarts=1, max_iter=10, calibration_folds=2, calibration_refit=False
        ),
    )
    return str(out)


@pytest.mark.parametrize("variant", VARIANTS)
def test_wrappers_pass_both_env_checkers(models: str, variant: str) -> None:
    env = make_belief_env(variant, models=models)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.filterwarnings("ignore", message=".*is different from the unwrapped version.*")
        check_env(env)
        sb3_check_env(env, warn=True)
    obs, _ = env.reset(seed=0)
    assert obs.dtype == np.float32 and env.observation_space.contains(obs)


def test_in_process_belief_equals_the_filter_run_by_hand(models: str) -> None:
    env = make_belief_env("belief", models=models)
    filt = build_filter("ekf", "gp", models)
    _, info = env.reset(seed=3)
    belief = GaussianBelief(info["state"], np.diag(INIT_STD**2))
    rng = np.random.default_rng(0)
    for _ in range(40):
        a = rng.uniform(-1, 1, 3).astype(np.float32)
        _, _, _, _, info = env.step(a)
        raw = env.unwrapped._last_obs
        z, valid = raw["ellipses"].reshape(-1).astype(np.float64), np.repeat(raw["valid"].astype(bool), 5)
        belief, _ = filt.step(belief, np.clip(a.astype(np.float64), -1, 1), z, valid)
        np.testing.assert_array_equal(info["belief_mean"], belief.mean)


@pytest.mark.parametrize("algo", ["ppo", "sac"])
@pytest.mark.parametrize("variant", VARIANTS)
def test_learn_256_steps_on_every_variant(models: str, algo: str, variant: str, tmp_path: Path) -> None:
    path = train_agent(
        AgentSpec(algo=algo, variant=variant, models=models),
        256,
        tmp_path,
        eval_freq=128,
        eval_episodes=1,
        progress_bar=False,
    )
    assert path.exists() and (tmp_path / "learning_curve.png").exists()


def test_saved_agent_reloads_and_acts_deterministically(models: str, tmp_path: Path) -> None:
    spec = AgentSpec(algo="ppo", variant="belief", models=models, seed=1)
    path = train_agent(spec, 256, tmp_path, eval_freq=10_000, progress_bar=False)
    a1, _ = load_agent(path)
    a2, spec2 = load_agent(path)
    assert spec2 == spec
    env = make_belief_env("belief", models=models)
    obs, _ = env.reset(seed=0)
    for _ in range(10):
        act1, _ = a1.predict(obs, deterministic=True)
        act2, _ = a2.predict(obs, deterministic=True)
        np.testing.assert_array_equal(act1, act2)
        obs, *_ = env.step(act1)
    first = evaluate_agent(path, episodes=1)
    assert first == evaluate_agent(path, episodes=1)
    assert np.isfinite(first["belief_position_rms_mm"])
    moved = tmp_path / "elsewhere"  # the spec's model folder resolves against the agent's folder
    moved.mkdir()
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(moved)
        assert load_agent(Path("..") / path.name)[1] == spec
    # a model file is loaded by its name (beside agent.json, or a checkpoint in checkpoints/)
    with torch.no_grad():
        for p in a1.policy.parameters():
            p.add_(1.0)
    for other in (tmp_path / "other.zip", tmp_path / "checkpoints" / "agent_7_steps.zip"):
        a1.save(other)
        a3, spec3 = load_agent(other)
        assert spec3 == spec
        for p1, p2, p3 in zip(
            a1.policy.parameters(), a2.policy.parameters(), a3.policy.parameters(), strict=True
        ):
            assert torch.equal(p3, p1) and not torch.equal(p3, p2)


OBS_TOL = {"rtol": 1e-4, "atol": 1e-5}  # batched vs one-at-a-time observations (float32 beliefs)


@pytest.mark.parametrize(("variant", "filt"), [(v, "ekf") for v in VARIANTS] + [("belief", "ukf")])
def test_batched_belief_env_equals_one_env_at_a_time(models: str, variant: str, filt: str) -> None:
    """Native batched simulator and batched filter step vs SB3's DummyVecEnv of single
    belief envs: observations, rewards, dones, terminal observations, episode records and
    beliefs over 300 steps with crashes and truncations (240 steps) of every blimp.

    The simulator is equal bit for bit. A batched model call rounds differently from one
    query, and this 60-point GP-EKF, flown far outside its data by random actions, grows
    that rounding to at most 1.7e-5 (of the covariance's largest entry, or metres) in 300
    steps; the parametric EKF to 2.9e-9, the GP-UKF to 1.6e-11. The adaptive factor
    integrates NIS/dof, so its rounding accumulates while it is above its floor: referred to
    this tiny GP's calibrated level (0.33) it is off the floor most of the time (growth
    1.7e-5); referred to 1, as before the reference existed, it sat at the floor (1.8e-7)."""
    spec = AgentSpec(variant=variant, models=models, filter=filt, seed=7)
    n = 3
    batched, single = make_vec(spec, n, batched=True), make_vec(spec, n, batched=False)
    obs, want = batched.reset(), single.reset()
    np.testing.assert_array_equal(obs, want)
    rng = np.random.default_rng(2)
    ends = 0
    for k in range(300):
        actions = rng.uniform(-1, 1, (n, 3)).astype(np.float32) * (1.0 if k % 120 > 60 else 0.2)
        obs, reward, done, infos = batched.step(actions)
        want, want_reward, want_done, want_infos = single.step(actions)
        np.testing.assert_allclose(obs, want, **OBS_TOL)  # float32 of the beliefs below
        for b, env in zip(batched.unwrapped.beliefs() or [], single.envs, strict=False):
            want_b = env.env.belief()  # a batched model call vs one query: rounding, grown below
            np.testing.assert_allclose(b.mean, want_b.mean, rtol=0, atol=1e-4)
            np.testing.assert_allclose(b.cov, want_b.cov, rtol=0, atol=1e-4 * np.abs(want_b.cov).max())
        np.testing.assert_array_equal(reward, want_reward)
        np.testing.assert_array_equal(done, want_done)
        for got, exp in zip(infos, want_infos, strict=True):
            assert got["TimeLimit.truncated"] == exp["TimeLimit.truncated"]
            assert ("terminal_observation" in got) == ("terminal_observation" in exp)
            if "terminal_observation" in exp:
                ends += 1
                last, want_last = got["terminal_observation"], exp["terminal_observation"]
                np.testing.assert_allclose(last, want_last, **OBS_TOL)
                assert got["episode"]["l"] == exp["episode"]["l"]  # VecMonitor sums float32 rewards
                assert got["episode"]["r"] == pytest.approx(exp["episode"]["r"], abs=1e-4)
                assert got["is_success"] == exp["is_success"]
    assert ends >= n
    batched.close()
    single.close()


def test_sb3_vector_env_gives_each_sub_env_its_own_filter(models: str) -> None:
    venv = make_vec(AgentSpec(variant="belief", models=models), n_envs=2, batched=False)
    obs = venv.reset()
    assert obs.shape == (2, 30) and not np.array_equal(obs[0], obs[1])
    filters = [e.env._filter for e in venv.envs]
    assert filters[0] is not filters[1]
    venv.close()


def test_service_back_end_gives_the_same_observations(models: str) -> None:
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "estimator_service", "--models", models, "--listen", f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert "ready" in proc.stdout.readline()
        session = open_session([f"tcp/127.0.0.1:{port}"])
        time.sleep(0.2)
        remote = make_belief_env("belief", models=models, backend="service", client=session)
        local = make_belief_env("belief", models=models)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            warnings.filterwarnings("ignore", message=".*is different from the unwrapped version.*")
            sb3_check_env(remote, warn=True)
        o1, _ = remote.reset(seed=5)
        o2, _ = local.reset(seed=5)
        np.testing.assert_array_equal(o1, o2)
        rng = np.random.default_rng(0)
        for _ in range(30):
            a = rng.uniform(-1, 1, 3).astype(np.float32)
            o1, *_ = remote.step(a)
            o2, *_ = local.step(a)
            np.testing.assert_array_equal(o1, o2)
        remote.close()
        session.close()
        # an endpoint instead of a live session: picklable, so SB3's SubprocVecEnv runs it
        from stable_baselines3.common.vec_env import SubprocVecEnv

        endpoint = f"tcp/127.0.0.1:{port}"
        fns = [lambda: make_belief_env("belief", models=models, backend="service", client=endpoint)] * 2
        venv = SubprocVecEnv(fns, start_method="spawn")
        venv.seed(5)
        first = venv.reset()
        for _ in range(5):
            obs, *_ = venv.step(np.zeros((2, 3), dtype=np.float32))
        venv.close()
        assert np.all(np.isfinite(obs)) and not np.array_equal(first, obs)
    finally:
        proc.terminate()
        proc.wait(timeout=20)


def test_collect_records_an_agents_flight_in_the_training_format(models: str, tmp_path: Path) -> None:
    from agents.cli import main as gpbf
    from estimator_service.flight import load_flight
    from estimator_service.training import prediction_data

    path = train_agent(
        AgentSpec(algo="ppo", variant="belief", models=models),
        256,
        tmp_path / "a",
        eval_freq=10_000,
        progress_bar=False,
    )
    out = tmp_path / "agent_flight.npz"
    assert gpbf(["collect", "--agent", str(path), "--minutes", "0.5", "--out", str(out), "--quiet"]) == 0
    flight = load_flight(out)
    assert flight.metadata["pilot"] == "agent" and len(flight) == 121
    x, y = prediction_data([flight])
    assert x.shape == (len(flight.transition_rows()), 15) and x.shape[0] >= 60 and np.all(np.isfinite(y))


def test_registered_ids_build_every_variant_and_hyperparams_cover_them(models: str) -> None:
    import gymnasium as gym

    from agents.rl import agent_env_id
    from agents.rl.hyperparams import load_hyperparams

    for task in ("hover", "waypoint"):
        for variant in VARIANTS:
            env_id = agent_env_id(task, variant)
            env = gym.make(env_id, models=models)
            obs, _ = env.reset(seed=0)
            assert env.unwrapped.config.task == task and env.observation_space.contains(obs)
            for algo in ("ppo", "sac"):
                params = load_hyperparams(algo, env_id)
                assert params.policy == "MlpPolicy" and params.n_timesteps == 1_000_000
    with pytest.raises(ValueError, match="needs a model folder"):
        gym.make(agent_env_id("hover", "belief"))
    with pytest.raises(ValueError, match="variant"):
        agent_env_id("hover", "telepathy")


def test_linear_schedules_are_read_as_rl_zoo3_reads_them(tmp_path: Path) -> None:
    """``lin_<x>`` starts at x and falls linearly to 0 over training (SB3's progress_remaining
    runs 1 -> 0), survives pickling with the agent, and numbers stay numbers."""
    import pickle

    from agents.rl.hyperparams import LinearSchedule, load_hyperparams

    file = tmp_path / "ppo.yml"
    file.write_text("x-v0:\n  learning_rate: lin_3e-4\n  clip_range: 0.2\n  clip_range_vf: null\n")
    params = load_hyperparams("ppo", "x-v0", file)
    lr = params.kwargs["learning_rate"]
    assert isinstance(lr, LinearSchedule) and params.kwargs["clip_range"] == 0.2
    assert params.kwargs["clip_range_vf"] is None  # SB3's "no value clipping" stays allowed
    assert [lr(p) for p in (1.0, 0.5, 0.0)] == pytest.approx([3e-4, 1.5e-4, 0.0])
    assert pickle.loads(pickle.dumps(lr)) == lr


def test_hyperparameter_files_refuse_what_train_agent_cannot_honour(tmp_path: Path) -> None:
    from agents.rl.hyperparams import load_hyperparams

    bad = tmp_path / "ppo.yml"
    for text, match in (
        ("x-v0:\n  frame_stack: 4\n", "'frame_stack'"),
        ('x-v0:\n  normalize: "dict(norm_obs=True)"\n', "normalize must be"),
        ("x-v0:\n  normalize: {norm_obs: 1}\n", "true or false"),
        ("x-v0:\n  n_envs: 0\n", "n_envs"),
        ('x-v0:\n  policy_kwargs: "dict(net_arch=[8])"\n', "policy_kwargs"),
        ("y-v0: {}\n", "no entry for 'x-v0'"),
        ("x-v0:\n  learning_rate: lin_fast\n", "learning_rate must be a positive number or 'lin_"),
        ("x-v0:\n  clip_range: -0.2\n", "clip_range must be"),
        ("x-v0:\n  learning_rate: lin_nan\n", "learning_rate must be"),
        ("x-v0:\n  learning_rate: .inf\n", "learning_rate must be"),
        ('x-v0:\n  learning_rate: "3e-4"\n', "learning_rate must be"),
        ("x-v0:\n  learning_rate: null\n", "learning_rate must be"),
        (
            "just some text\n",
            "no entry for 'x-v0' \\(no mapping of env ids\\)",
        ),  # a text file: was a KeyError
        ("x-v0: [1, 2\n", "is not YAML"),
        ("x-v0: 5\n", "expected a mapping"),
    ):
        bad.write_text(text)
        with pytest.raises(ValueError, match=match):
            load_hyperparams("ppo", "x-v0", bad)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_hyperparams("ppo", "x-v0", tmp_path / "none.yml")
    bad.write_text("x-v0: {}\n" + "#" * 1_000_001)  # parsing cost is bounded by a size cap
    with pytest.raises(ValueError, match="over 1000000 bytes"):
        load_hyperparams("ppo", "x-v0", bad)


@pytest.mark.parametrize(
    ("args", "field"), [(["--tasks", "hover,orbit"], "--tasks"), (["--variants", "sonar"], "--variants"),
                        (["--seeds", "0"], "--seeds"), (["--jobs", "-1"], "--jobs")],
)  # fmt: skip
def test_rl_experiment_refuses_bad_options_naming_them(
    args: list[str], field: str, tmp_path: Path, capsys
) -> None:
    from agents.experiments.rl import main as rl_main

    with pytest.raises(SystemExit) as e:
        rl_main(["--out", str(tmp_path / "out"), "--report-only", *args])
    assert e.value.code == 2 and field in capsys.readouterr().err
    assert not (tmp_path / "out").exists()  # refused before any work


@pytest.mark.parametrize(
    ("algo", "env_id", "extra"),
    [
        ("sac", "gpbf_env/Blimp-v0", ["--gym-packages", "gpbf_env", "-params", "learning_starts:64"]),
        (
            "ppo",
            "gpbf_agents/BlimpBelief-v0",
            ["--gym-packages", "agents.rl", "-params", "n_steps:16", "n_envs:2"],
        ),
    ],
)
def test_rl_zoo3_trains_on_the_env_with_the_committed_hyperparameters(
    models: str, algo: str, env_id: str, extra: list[str], tmp_path: Path
) -> None:
    """The issue's command, at a 128-step budget: rl-zoo3 reads hyperparams/<algo>.yml,
    builds the env (the belief variant through its registered id and --env-kwargs),
    trains and saves."""
    root = Path(__file__).resolve().parents[1]
    cmd = [
        sys.executable, "-m", "rl_zoo3.train", "--algo", algo, "--env", env_id,
        "--conf-file", str(root / "hyperparams" / f"{algo}.yml"), "-n", "128", "--seed", "0",
        "--eval-freq", "-1", "--log-folder", str(tmp_path), "--device", "cpu", *extra,
    ]  # fmt: skip
    if env_id.startswith("gpbf_agents"):
        cmd += ["--env-kwargs", f"models:{models!r}"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    assert list(tmp_path.glob(f"{algo}/*_1/*.zip")), out.stdout[-2000:]


def _no_bare_constant(name: str) -> None:
    pytest.fail(f"bare {name} in a JSON file (not standard JSON)")


def test_rl_experiment_and_agent_data_loop_smoke(
    models: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Tiny budgets: results.json holds per task and variant the success rate and mean
    return, the pilot's figures and the targets; the report, both figures and the
    agent-data table are written; the command the report prints for an agent gives its
    figures, and the train-agent command it prints trains the same agent, parameter for
    parameter (without ``--threads 1`` a PPO agent's parameters differ)."""
    import json
    import shutil
    from dataclasses import replace

    from agents.experiments.agent_data import agent_data_loop
    from agents.experiments.rl import RLSettings, report_existing, run
    from agents.experiments.rl_report import write_report
    from estimator_service.training import TrainSettings

    shutil.copytree(models, tmp_path / "models")
    cfg = RLSettings(
        timesteps=256, seeds=1, episodes=1, tasks=("hover",), variants=("state", "belief", "ellipses"),
        points=60, model="gp", jobs=1,
    )  # fmt: skip
    import agents.experiments.rl as rl_module

    versions = iter(["abc0001", "abc0002"])  # the checkout moves on while the agents train
    monkeypatch.setattr(rl_module, "code_version", lambda: next(versions))
    run(tmp_path, cfg)
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["provenance"]["code"] == "abc0001"  # the code that trained them
    record = json.loads((tmp_path / "agents" / "hover-belief-0" / "run.json").read_text())
    assert record["versions"]["code"] == "abc0001"  # the experiment's, not the worker's own reading
    assert " ".join(record["command"]) == data["provenance"]["command"]  # not the process pool's
    hover = data["results"]["hover"]
    assert set(hover) == {"state", "belief", "ellipses"}
    assert all(0 <= hover[v]["success_rate"] <= 1 and np.isfinite(hover[v]["mean_return"]) for v in hover)
    assert np.isfinite(data["pilot"]["hover"]["mean_return"]) and "hover" in data["gap_closed"]
    assert "hover_state_success_ge_0.9" in data["targets"]
    assert data["provenance"]["wall_s"] > 0 and "Provenance: code " in (tmp_path / "report.md").read_text()
    for written in [tmp_path / "results.json", *(tmp_path / "agents").glob("*/result.json")]:
        json.loads(written.read_text(), parse_constant=_no_bare_constant)
    partial = report_existing(tmp_path, replace(cfg, variants=("state", "belief-param")))
    assert partial["meta"]["not_trained"] == ["hover-belief-param-0"]
    assert partial["provenance"] == data["provenance"]  # the training run's, not the report's
    assert set(partial["results"]["hover"]) == {"state"}
    from agents.experiments.rl import main as rl_main

    assert (
        rl_main(
            ["--out", str(tmp_path), "--seeds", "1", "--tasks", "hover", "--episodes", "1", "--report-only"]
        )
        == 0
    )
    agent = tmp_path / "agents" / "hover-state-0" / "model.zip"
    tiny = TrainSettings(n_points=40, calibration_seconds=0.0)  # no calibration: test_calibration's subject
    loop = agent_data_loop(
        tmp_path, agent, scripted_minutes=1, agent_minutes=1, heldout_minutes=1, settings=tiny
    )
    assert set(loop["tracking"]) == {"scripted", "scripted+agent"} and loop["heldout_episodes"] >= 1
    assert loop["agent"] == "agents/hover-state-0"  # relative to the report: no machine's paths
    write_report(tmp_path, data)
    report = (tmp_path / "report.md").read_text()
    assert "agent-data loop" in report and "WaypointPilot" in report
    assert "agent `hover-state-0` flew" in report
    row = next(ln for ln in report.splitlines() if ln.startswith("| hover-state-0 | `gpbf eval-agent "))
    from agents.cli import main as gpbf_main

    capsys.readouterr()
    assert gpbf_main([*row.split("`")[1].split()[1:], "--quiet"]) == 0
    again = json.loads(capsys.readouterr().out)
    saved = json.loads((agent.parent / "result.json").read_text())
    assert again["mean_return"] == saved["mean_return"] and again["success_rate"] == saved["success_rate"]
    import torch

    from agents.rl.training import load_agent

    for name in ("hover-belief-0", "hover-state-0"):  # with a filter's models, and without
        train = next(ln for ln in report.splitlines() if ln.startswith(f"- {name}: `gpbf train-agent "))
        argv = train.split("`")[1].split()[1:]
        assert argv[argv.index("--out") + 1] == f"out/{name}" and ("--models" in argv) == ("belief" in name)
        argv[argv.index("--out") + 1] = str(tmp_path / "again" / name)
        assert gpbf_main([*argv, "--quiet"]) == 0  # the printed command trains the same agent
        mine, theirs = (
            load_agent(f)[0].policy.state_dict()
            for f in (tmp_path / "again" / name, agent.parent.parent / name)
        )
        assert mine.keys() == theirs.keys() and all(torch.equal(mine[k], theirs[k]) for k in mine), name
    from agents.experiments.report_notes import NOTES_MARKER

    (tmp_path / "report.md").write_text(f"{report}\n{NOTES_MARKER}\n## Reading the table\n")
    write_report(tmp_path, data)  # regenerated: the hand-written section stays
    assert (tmp_path / "report.md").read_text().endswith(f"\n{NOTES_MARKER}\n## Reading the table\n")
    assert (tmp_path / "learning_curves.png").exists() and (tmp_path / "returns.png").exists()


def test_a_resumed_rl_run_counts_the_agents_it_finds_trained_as_a_sliver_of_the_work(tmp_path: Path) -> None:
    """A run resumed with 3 of its 9 agents trained reads them back in seconds; its progress
    must not say a third of the work is done (it said 33 % with an ETA of 10 s on a run with
    about 90 minutes left), and the agents left weigh by variant."""
    import io

    from agents.experiments.rl import FILTER_VARIANT_COST, agent_weights
    from estimator_service.progress import ProgressBar

    todo = [("hover", v, s) for v in ("state", "belief", "ellipses") for s in range(3)]
    for s in range(3):
        (tmp_path / "agents" / f"hover-state-{s}").mkdir(parents=True)
        (tmp_path / "agents" / f"hover-state-{s}" / "result.json").write_text("{}")
    weights = agent_weights(tmp_path, todo)
    assert weights[3:] == [FILTER_VARIANT_COST] * 3 + [1.0] * 3
    stream = io.StringIO()
    bar = ProgressBar("train agents", unit="agent", weights=weights, stream=stream)
    for i in range(3):
        bar.advance(index=i)
    bar.close()
    assert "3/9 agents (0%)" in stream.getvalue().splitlines()[-1]


def test_tensorboard_flag_logs_or_names_the_missing_package(models: str, tmp_path: Path) -> None:
    import importlib.util

    spec = AgentSpec(algo="ppo", variant="state", models=models)
    if importlib.util.find_spec("tensorboard") is None:
        with pytest.raises(ModuleNotFoundError, match="pip install tensorboard"):
            train_agent(spec, 128, tmp_path / "agent", tensorboard=tmp_path / "tb", progress_bar=False)
        assert not (tmp_path / "agent").exists()  # refused before any work
    else:
        train_agent(spec, 128, tmp_path / "agent", tensorboard=tmp_path / "tb", progress_bar=False)
        assert list((tmp_path / "tb").rglob("events.out.tfevents.*"))


def test_learning_curves_align_seeds_evaluated_at_different_intervals(tmp_path: Path) -> None:
    from agents.experiments.rl_report import learning_curves

    def evaluated(seed: int, every: int) -> None:  # a linear curve: return = step / 1000
        folder = tmp_path / "agents" / f"hover-state-{seed}"
        folder.mkdir(parents=True)
        steps = np.arange(every, 1_000_001, every)
        np.savez(
            folder / "evaluations.npz", timesteps=steps, results=np.repeat(steps[:, None] / 1e3, 4, axis=1)
        )

    evaluated(0, 50_000)
    evaluated(1, 100_000)
    steps, returns = learning_curves(tmp_path, "hover", "state")
    np.testing.assert_array_equal(steps, np.arange(100_000, 1_000_001, 100_000))
    np.testing.assert_array_equal(returns, np.stack([steps / 1e3, steps / 1e3]))  # each at its own step
    evaluated(2, 4_992)  # train-agent's default: a multiple of 16 blimps, no step in common
    steps, returns = learning_curves(tmp_path, "hover", "state")
    np.testing.assert_array_equal(steps, np.arange(100_000, 998_401, 100_000))  # the span all seeds cover
    np.testing.assert_allclose(returns, np.stack([steps / 1e3] * 3))  # a linear curve, interpolated


def test_normalize_is_read_applied_saved_and_used_when_the_agent_acts(tmp_path: Path) -> None:
    """rl-zoo3's ``normalize`` key: SB3's ``VecNormalize`` during training, its statistics
    saved beside the agent and applied, frozen, whenever the saved agent acts."""
    from stable_baselines3.common.vec_env import VecNormalize

    from agents.rl.hyperparams import load_hyperparams
    from agents.rl.registry import agent_env_id
    from agents.rl.training import NORMALIZER_FILE, _evaluate, observation_normalizer

    env_id = agent_env_id("hover", "state")
    conf = tmp_path / "ppo.yml"
    conf.write_text(
        f"{env_id}:\n  n_envs: 2\n  normalize: {{norm_reward: false}}\n  n_steps: 64\n  batch_size: 64\n"
    )
    params = load_hyperparams("ppo", env_id, conf)
    assert params.normalize == {"norm_obs": True, "norm_reward": False} and "normalize" not in params.kwargs
    conf.write_text(f"{env_id}:\n  n_envs: 2\n  normalize: true\n  n_steps: 64\n  batch_size: 64\n")
    assert load_hyperparams("ppo", env_id, conf).normalize == {"norm_obs": True, "norm_reward": True}
    spec = AgentSpec(algo="ppo", variant="state", seed=2)
    path = train_agent(spec, 6000, tmp_path / "a", eval_freq=10_000, progress_bar=False, hyperparams=conf)
    norm = VecNormalize.load(str(tmp_path / "a" / NORMALIZER_FILE), make_vec(spec, 1))
    assert norm.obs_rms.count > 6000  # statistics of every training step
    env = make_belief_env("state")
    obs, _ = env.reset(seed=0)
    want = np.clip((obs - norm.obs_rms.mean) / np.sqrt(norm.obs_rms.var + norm.epsilon), -10, 10)
    np.testing.assert_allclose(observation_normalizer(path)(obs), want, rtol=1e-5, atol=1e-5)
    agent, _ = load_agent(path)
    first = evaluate_agent(path, episodes=1)
    assert first == evaluate_agent(path, episodes=1)
    norm_obs = observation_normalizer(path)
    returns = [
        _evaluate(
            make_belief_env("state"),
            lambda o, _, f=f: agent.predict(f(o), deterministic=True)[0],
            1,
            1000,
            None,
        )
        for f in (norm_obs, lambda o: o)
    ]
    assert returns[0]["mean_return"] == pytest.approx(first["mean_return"])
    assert returns[1]["mean_return"] != pytest.approx(first["mean_return"])  # what the agent sees matters
    assert observation_normalizer(tmp_path)(obs) is obs  # an agent trained without it


def test_a_run_records_its_command_and_resumes_from_its_newest_checkpoint(models: str, tmp_path) -> None:
    """``run.json`` holds the command line, settings and versions; checkpoints keep only the
    newest replay buffer; ``resume`` continues from the newest checkpoint (model, replay
    buffer, learning curve) to the total budget."""
    import json

    from agents.rl.training import latest_checkpoint

    spec = AgentSpec(algo="sac", variant="belief", models=models, seed=2)
    out = tmp_path / "agent"
    with pytest.raises(FileNotFoundError, match="no complete checkpoint in"):
        train_agent(spec, 256, out, resume=True, progress_bar=False)
    train_agent(spec, 256, out, eval_freq=64, eval_episodes=1, checkpoint_freq=64, progress_bar=False,
                command=["gpbf", "train-agent", "--algo", "sac"])  # fmt: skip
    run = json.loads((out / "run.json").read_text())
    assert run["command"][:2] == ["gpbf", "train-agent"] and run["checkpoint_freq"] == 64
    assert run["resumed_from_steps"] is None and {"torch", "stable_baselines3"} <= set(run["versions"])
    assert latest_checkpoint(out)[1] == 256
    buffers = [f.name for f in (out / "checkpoints").glob("*replay_buffer*")]
    assert buffers == ["agent_replay_buffer_256_steps.pkl"]
    assert latest_checkpoint(out, ("replay_buffer",))[1] == 256
    (out / "checkpoints" / "agent_320_steps.zip").write_bytes(b"")  # a run stopped before its buffer
    assert latest_checkpoint(out, ("replay_buffer",))[1] == 256 and latest_checkpoint(out)[1] == 320
    (out / "checkpoints" / "agent_320_steps.zip").unlink()
    before = np.load(out / "evaluations.npz")["timesteps"].tolist()
    train_agent(spec, 384, out, eval_freq=64, eval_episodes=1, checkpoint_freq=64, progress_bar=False,
                resume=True)  # fmt: skip
    agent, _ = load_agent(out)
    assert agent.num_timesteps == 384
    run = json.loads((out / "run.json").read_text())
    assert run["resumed_from_steps"] is None and run["command"][:2] == [
        "gpbf",
        "train-agent",
    ]  # the first run's
    assert [r["resumed_from_steps"] for r in run["resumes"]] == [256]
    assert "/" not in run["resumes"][0]["command"][0]  # this process's program, by its name only
    after = np.load(out / "evaluations.npz")["timesteps"].tolist()
    assert before == [64, 128, 192, 256] and after == [*before, 320, 384]


@pytest.mark.slow
@pytest.mark.parametrize("folder", ["sac_hover", "rl"])
def test_a_published_agent_gives_the_figures_its_report_prints(
    folder: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """The command a published report (SAC; PPO, whose hover agents carry their
    observation normaliser) prints for one agent (``gpbf eval-agent ... --episodes 100
    --seed 5000 --threads 1``) returns that agent's recorded figures: the committed files
    still load and fly as they did (a change to the simulator or the observations fails here
    until the agents are trained again). Equal to the last digit on the machine that trained
    them; another CPU's rounding may move single episodes, so the mean return is held to
    three standard errors of its episodes and the success rate to 0.05."""
    import json

    from agents.cli import main as gpbf_main

    root = Path(__file__).resolve().parents[1]
    report = (root / "docs" / "results" / folder / "report.md").read_text()
    cmd = next(ln for ln in report.splitlines() if ln.startswith("| hover-state-1 |")).split("`")[1].split()
    assert cmd[:2] == ["gpbf", "eval-agent"]
    assert cmd[3:] == ["--episodes", "100", "--seed", "5000", "--threads", "1"]
    model = root / cmd[2]
    capsys.readouterr()
    assert gpbf_main(["eval-agent", str(model), *cmd[3:], "--quiet"]) == 0
    res = json.loads(capsys.readouterr().out)
    saved = json.loads((model.parent / "result.json").read_text())
    assert abs(res["mean_return"] - saved["mean_return"]) <= 3 * saved["std_return"] / 10, (res, saved)
    assert abs(res["success_rate"] - saved["success_rate"]) <= 0.05 and saved["success_rate"] >= 0.9
