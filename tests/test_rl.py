"""Belief wrappers, both back ends, and stable-baselines3 training on beliefs."""

from __future__ import annotations

import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
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
        settings=TrainSettings(n_points=60, n_pseudo=8, restarts=1, max_iter=10),
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


def test_sb3_vector_env_gives_each_sub_env_its_own_filter(models: str) -> None:
    venv = make_vec(AgentSpec(variant="belief", models=models), n_envs=2)
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
