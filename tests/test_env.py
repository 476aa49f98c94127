"""Blimp environment: Gymnasium contracts, determinism, vector envs, physics sanity."""

from __future__ import annotations

import dataclasses
import math
import pickle
import re
import subprocess
import sys
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import gpbf_env
from gpbf_env import BlimpParams

ENV_ID = "gpbf_env/Blimp-v0"
REALITIES = ["clean", "lab"]


def rollout(env: gym.Env, seed: int, steps: int, action_seed: int = 1):
    rng = np.random.default_rng(action_seed)
    obs, info = env.reset(seed=seed)
    out = [(obs["ellipses"].copy(), obs["valid"].copy(), 0.0, info["state"])]
    for _ in range(steps):
        obs, r, term, trunc, info = env.step(rng.uniform(-1, 1, 3).astype(np.float32))
        out.append((obs["ellipses"].copy(), obs["valid"].copy(), r, info["state"]))
        if term or trunc:
            obs, info = env.reset()
    return out


@pytest.mark.parametrize("env_id", [ENV_ID, "gpbf_env/BlimpWaypoint-v0"])
@pytest.mark.parametrize("render_mode", [None, "rgb_array"])
@pytest.mark.parametrize("reality", REALITIES)
def test_check_env_without_warnings(env_id: str, render_mode: str | None, reality: str) -> None:
    env = gym.make(env_id, render_mode=render_mode, reality=reality)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)
    if render_mode:
        env.reset(seed=0)
        img = env.render()
        assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3


def test_make_with_module_prefix_in_fresh_process() -> None:
    code = (
        "import gymnasium as gym, sys; e = gym.make('gpbf_env:gpbf_env/Blimp-v0');"
        "o, i = e.reset(seed=0); assert i['state'].shape == (12,);"
        "assert 'gpbf_env' in sys.modules"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


@pytest.mark.parametrize("reality", REALITIES)
def test_same_seed_same_rollout_and_different_seed_differs(reality: str) -> None:
    a = rollout(gym.make(ENV_ID, reality=reality), 7, 300)
    b = rollout(gym.make(ENV_ID, reality=reality), 7, 300)
    c = rollout(gym.make(ENV_ID, reality=reality), 8, 300)
    for x, y in zip(a, b, strict=True):
        for u, v in zip(x, y, strict=True):
            np.testing.assert_array_equal(u, v)
    assert not np.allclose(a[-1][3], c[-1][3])


@pytest.mark.parametrize("reality", REALITIES)
def test_pickle_mid_episode_continues_identically(reality: str) -> None:
    env = gym.make(ENV_ID, reality=reality)
    env.reset(seed=3)
    for _ in range(20):
        env.step(np.array([0.5, 0.2, -0.3], dtype=np.float32))
    clone = pickle.loads(pickle.dumps(env))
    for _ in range(30):
        a = np.array([0.8, -0.1, 0.4], dtype=np.float32)
        o1, r1, *_, i1 = env.step(a)
        o2, r2, *_, i2 = clone.step(a)
        assert r1 == r2
        np.testing.assert_array_equal(i1["state"], i2["state"])
        np.testing.assert_array_equal(i1["mocap"], i2["mocap"])
        np.testing.assert_array_equal(o1["ellipses"], o2["ellipses"])


@pytest.mark.parametrize("reality", REALITIES)
def test_native_vector_env_matches_single_envs_including_autoreset(reality: str) -> None:
    n, steps, seed = 3, 400, 11
    venv = gym.make_vec(ENV_ID, num_envs=n, max_episode_steps=50, reality=reality)
    assert isinstance(venv.unwrapped, gpbf_env.BlimpVectorEnv)
    singles = [gym.make(ENV_ID, max_episode_steps=50, reality=reality) for _ in range(n)]
    vo, vi = venv.reset(seed=seed)
    for i, env in enumerate(singles):
        o, info = env.reset(seed=seed + i)
        np.testing.assert_allclose(vi["state"][i], info["state"], atol=1e-12)
    rng = np.random.default_rng(0)
    done = np.zeros(n, dtype=bool)
    n_resets = 0
    for _ in range(steps):
        actions = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
        vo, vr, vterm, vtrunc, vi = venv.step(actions)
        for i, env in enumerate(singles):
            if done[i]:  # next-step autoreset: the vector env reset this blimp
                o, info = env.reset()
                r, term, trunc, state = 0.0, False, False, info["state"]
                n_resets += 1
            else:
                o, r, term, trunc, info = env.step(actions[i])
                state = info["state"]
            # one compiled kernel for both: equal here; 1e-12 allows a vectorised blimp loop
            np.testing.assert_allclose(vi["state"][i], state, rtol=0, atol=1e-12)
            np.testing.assert_allclose(vi["mocap"][i], info["mocap"], rtol=0, atol=1e-12)
            np.testing.assert_allclose(vo["ellipses"][i], o["ellipses"], rtol=0, atol=1e-4)
            np.testing.assert_array_equal(vo["valid"][i], o["valid"])
            assert (vterm[i], vtrunc[i]) == (term, trunc)
            assert vr[i] == pytest.approx(r, abs=1e-9)
        done = vterm | vtrunc
    assert n_resets >= n * 5


def test_sync_make_vec_and_sb3_vec_envs() -> None:
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    sync = gym.make_vec(ENV_ID, num_envs=2, vectorization_mode="sync")
    sync.reset(seed=0)
    obs, *_ = sync.step(np.zeros((2, 3), dtype=np.float32))
    assert obs["ellipses"].shape == (2, 2, 5)
    for cls in (DummyVecEnv, SubprocVecEnv):
        venv = make_vec_env("gpbf_env:" + ENV_ID, n_envs=2, seed=0, vec_env_cls=cls)
        obs = venv.reset()
        for _ in range(5):
            obs, rew, _dones, infos = venv.step(np.zeros((2, 3), dtype=np.float32))
        assert obs["ellipses"].shape == (2, 2, 5) and rew.shape == (2,)
        assert infos[0]["state"].shape == (12,)
        venv.close()


def test_halving_the_integration_step_moves_60s_by_under_1cm() -> None:
    def final_position(substeps: int) -> np.ndarray:
        env = gym.make(ENV_ID, substeps=substeps, max_episode_steps=None)
        env.reset(seed=5, options={"state": [5, 3, 2, 0.2, -0.1, 0.5, 0, 0, 0, 0, 0, 0]})
        rng = np.random.default_rng(2)
        for k in range(240):
            a = rng.uniform(-1, 1, 3) if k % 8 == 0 else a  # noqa: F821 - held for 2 s
            *_, info = env.step(a.astype(np.float32))
        return info["state"][:3]

    default = gpbf_env.WorldConfig().substeps
    shift = np.linalg.norm(final_position(default) - final_position(2 * default))
    assert shift < 0.01


@pytest.mark.parametrize("reality", ["clean", "lab"])
def test_unpowered_blimp_self_rights_and_settles(reality: str) -> None:
    calm = dataclasses.replace(BlimpParams(), gust_std=0.0, buoyancy_ratio=1.0)
    env = gym.make(ENV_ID, params=calm, max_episode_steps=None, reality=reality)
    env.reset(seed=0, options={"state": [5, 3, 2, 0.5, -0.4, 0.0, 0.3, 0, 0, 0.5, -0.3, 0.2]})
    states = []
    for _ in range(240):
        *_, info = env.step(np.array([0.0, 0.0, 0.0], dtype=np.float32))
        states.append(info["state"])
    s = np.array(states)
    trim = 0.0 if reality == "clean" else -math.atan(calm.cg_lateral / calm.cg_below_cb)  # U7
    assert np.max(np.abs(s[-40:, 3] - trim)) < 0.002  # roll back to its trim
    assert np.max(np.abs(s[-40:, 4])) < 0.02  # pitch back to level
    assert np.max(np.abs(s[-40:, 6:12])) < 0.02  # velocities die out
    kinetic = np.sum(s[:, 6:9] ** 2, axis=1) + np.sum(s[:, 9:12] ** 2, axis=1)
    assert kinetic[-1] < 1e-3 * kinetic[0]


def test_camera_schedule_is_staggered_at_one_hertz() -> None:
    env = gym.make(ENV_ID, max_episode_steps=None)
    env.reset(seed=1, options={"state": [5, 3, 1.8, 0, 0, 0, 0, 0, 0, 0, 0, 0]})
    valid = [env.step(np.zeros(3, dtype=np.float32))[0]["valid"] for _ in range(40)]
    v = np.array(valid)
    assert v.sum(axis=0).tolist() == [10, 10]  # 1 Hz each over 10 s
    assert not np.any(v.all(axis=1))  # never both at once


def test_leaving_the_room_terminates() -> None:
    env = gym.make(ENV_ID)
    env.reset(seed=0, options={"state": [5, 3, 3.55, 0, 0, 0, 0, 0, 0.5, 0, 0, 0]})
    terminated = False
    for _ in range(20):
        _, reward, terminated, _, info = env.step(np.array([1, 1, 0], dtype=np.float32))
        if terminated:
            break
    assert terminated and info["crashed"] and reward < -18  # the crash penalty outweighs the alive bonus


@pytest.mark.parametrize(
    "action",
    [np.array([np.nan, 0, 0]), np.array([0, np.inf, 0]), np.zeros(2), np.zeros((1, 3))],
)
def test_bad_actions_raise_and_change_nothing(action: np.ndarray) -> None:
    env = gym.make(ENV_ID)
    env.reset(seed=0)
    before = env.unwrapped.state
    with pytest.raises(ValueError, match="action"):
        env.unwrapped.step(action)
    np.testing.assert_array_equal(env.unwrapped.state, before)


def test_out_of_range_actions_are_clipped() -> None:
    results = []
    for a in ([5.0, -3.0, 2.0], [1.0, -1.0, 1.0]):
        env = gym.make(ENV_ID)
        env.reset(seed=4)
        for _ in range(10):
            *_, info = env.step(np.array(a, dtype=np.float32))
        results.append(info["state"])
    np.testing.assert_array_equal(results[0], results[1])


def test_domain_randomisation_is_seeded() -> None:
    env = gym.make(ENV_ID, randomize=0.2)
    env.reset(seed=1)
    p1 = env.unwrapped.params
    env.reset(seed=1)
    assert env.unwrapped.params == p1
    env.reset(seed=2)
    assert env.unwrapped.params != p1
    assert env.unwrapped.params.semi_length == p1.semi_length  # geometry is kept


def test_rendered_camera_mode_agrees_with_closed_form_mode() -> None:
    """The slow mode (noisy image, background subtraction, fit) sees the same ellipses."""
    start = {"state": [5.0, 3.0, 1.8, 0.05, -0.05, 0.7, 0, 0, 0, 0, 0, 0]}
    calm = dataclasses.replace(BlimpParams(), gust_std=0.0)  # same states in both envs
    fast = gym.make(ENV_ID, params=calm, pixel_noise=0.0, max_episode_steps=None)
    slow = gym.make(ENV_ID, params=calm, camera_mode="rendered", max_episode_steps=None)
    fast.reset(seed=0, options=start)
    slow.reset(seed=0, options=start)
    seen = 0
    for _ in range(8):
        a = np.array([0.4, 0.2, 0.3], dtype=np.float32)
        of, *_, inf_f = fast.step(a)
        os_, *_, inf_s = slow.step(a)
        np.testing.assert_array_equal(inf_f["state"], inf_s["state"])
        np.testing.assert_array_equal(of["valid"], os_["valid"])
        for k in np.flatnonzero(of["valid"]):
            np.testing.assert_allclose(os_["ellipses"][k, :4], of["ellipses"][k, :4], atol=3.0)
            seen += 1
    assert seen >= 3


ENV_IDS = [ENV_ID, "gpbf_env/BlimpWaypoint-v0"]


def test_native_vector_env_renders_the_sync_vector_envs_frames() -> None:
    kwargs = {"num_envs": 2, "render_mode": "rgb_array", "max_episode_steps": 4}
    native = gym.make_vec(ENV_ID, vectorization_mode="vector_entry_point", **kwargs)
    sync = gym.make_vec(ENV_ID, vectorization_mode="sync", **kwargs)
    assert isinstance(native.unwrapped, gpbf_env.BlimpVectorEnv)
    assert native.render_mode == sync.render_mode == "rgb_array"
    assert native.metadata["render_modes"] == ["rgb_array"]
    assert native.metadata["render_fps"] == sync.metadata["render_fps"]
    native.reset(seed=5)
    sync.reset(seed=5)
    rng = np.random.default_rng(3)
    for _ in range(7):  # crosses the autoreset after step 4
        frames, expected = native.render(), sync.render()
        assert isinstance(frames, tuple) and len(frames) == 2
        for frame, want in zip(frames, expected, strict=True):
            assert frame.dtype == np.uint8 and frame.shape == want.shape
            np.testing.assert_array_equal(frame, want)
        actions = rng.uniform(-1, 1, (2, 3)).astype(np.float32)
        native.step(actions)
        sync.step(actions)
    assert gym.make_vec(ENV_ID, num_envs=2).render() is None
    with pytest.raises(ValueError, match="render_mode"):
        gym.make_vec(ENV_ID, num_envs=2, render_mode="human")


def _assert_same_info(got: dict, want: dict) -> None:
    assert set(got) == set(want)
    for key, value in want.items():
        actual = got[key]
        assert isinstance(actual, np.ndarray), key
        assert (actual.shape, actual.dtype) == (value.shape, value.dtype), key
        if np.issubdtype(value.dtype, np.floating):
            np.testing.assert_allclose(actual, value, rtol=0, atol=1e-9, err_msg=key)
        else:
            np.testing.assert_array_equal(actual, value, err_msg=key)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_native_vector_env_info_matches_sync_vector_env(env_id: str) -> None:
    n, seed = 3, 21
    native = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", max_episode_steps=30)
    sync = gym.make_vec(env_id, num_envs=n, vectorization_mode="sync", max_episode_steps=30)
    rng = np.random.default_rng(5)  # actions that crash some blimps and not others
    partial = all_reset = 0
    for k in range(300):
        if k % 100 == 0:
            _, info = native.reset(seed=seed + k)
            _, want = sync.reset(seed=seed + k)
            _assert_same_info(info, want)
        gentle = k % 100 <= 30  # no crash: all blimps truncate, and autoreset, together
        actions = rng.uniform(-1, 1, (n, 3)).astype(np.float32) * (0.1 if gentle else 1.0)
        _, reward, term, trunc, info = native.step(actions)
        _, want_reward, want_term, want_trunc, want = sync.step(actions)
        _assert_same_info(info, want)
        np.testing.assert_allclose(reward, want_reward, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(term | trunc, want_term | want_trunc)
        partial += "_crashed" in want and not want["_crashed"].all()
        all_reset += "crashed" not in want
    assert partial > 0 and all_reset > 0  # autoresets of some and of all blimps were compared


def _documented_info_keys() -> set[str]:
    doc = gpbf_env.BlimpEnv.__doc__ or ""
    section = doc.split("## Info", 1)[1].split("##", 1)[0] if "## Info" in doc else doc
    groups = re.findall(r"info\[([^\]]+)\]", section)  # info["a"] or info["a" | "b"]
    return {key for group in groups for key in re.findall(r'"(\w+)"', group)}


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_every_documented_info_key_is_returned(env_id: str) -> None:
    documented = _documented_info_keys()
    assert {"state", "t", "reward_alive"} <= documented  # the parser found the section
    env = gym.make(env_id)
    _, reset_info = env.reset(seed=0)
    *_, step_info = env.step(env.action_space.sample())
    assert set(reset_info) <= set(step_info) == documented
    venv = gym.make_vec(env_id, num_envs=2)
    _, vreset_info = venv.reset(seed=0)
    *_, vstep_info = venv.step(np.zeros((2, 3), dtype=np.float32))
    assert {k for k in vreset_info if not k.startswith("_")} == set(reset_info)
    assert {k for k in vstep_info if not k.startswith("_")} == documented


@pytest.mark.parametrize("reality", REALITIES)
def test_same_step_autoreset_matches_sync_vector_env(reality: str) -> None:
    """SB3's layout: an ended blimp is reset within the step, its last observation and
    info under ``final_obs``/``final_info``; every value equals the sync vector env's."""
    from gymnasium.vector import AutoresetMode

    n, mode = 3, AutoresetMode.SAME_STEP
    kwargs = {"num_envs": n, "max_episode_steps": 30, "reality": reality}
    native = gym.make_vec(ENV_ID, vectorization_mode="vector_entry_point", autoreset_mode=mode, **kwargs)
    sync = gym.make_vec(ENV_ID, vectorization_mode="sync", vector_kwargs={"autoreset_mode": mode}, **kwargs)
    assert native.metadata["autoreset_mode"] == mode
    rng = np.random.default_rng(5)
    native.reset(seed=3)
    sync.reset(seed=3)
    ended = 0
    for k in range(120):
        actions = rng.uniform(-1, 1, (n, 3)).astype(np.float32) * (0.1 if k < 40 else 1.0)
        obs, reward, term, trunc, info = native.step(actions)
        want_obs, want_reward, want_term, want_trunc, want = sync.step(actions)
        for key in ("ellipses", "valid"):
            np.testing.assert_allclose(obs[key], want_obs[key], rtol=0, atol=1e-4, err_msg=key)
        np.testing.assert_allclose(reward, want_reward, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(term | trunc, want_term | want_trunc)
        final, want_final = info.pop("final_obs", None), want.pop("final_obs", None)
        assert (final is None) == (want_final is None)
        if final is not None:
            np.testing.assert_array_equal(info.pop("_final_obs"), want.pop("_final_obs"))
            for i in np.flatnonzero(want_term | want_trunc):
                np.testing.assert_allclose(final[i]["ellipses"], want_final[i]["ellipses"], atol=1e-4)
            _assert_same_info(info.pop("final_info"), want.pop("final_info"))
            ended += int((want_term | want_trunc).sum())
        _assert_same_info(info, want)
    assert ended >= n  # every blimp ended at least once (truncation at 30 steps)
    with pytest.raises(ValueError, match="autoreset_mode"):
        gpbf_env.BlimpVectorEnv(2, autoreset_mode="sometimes")


def _waypoint_return(seed: int, pilot: bool) -> tuple[float, dict, int]:
    from agents.pilots import WaypointPilot

    env = gym.make("gpbf_env/BlimpWaypoint-v0")
    _, info = env.reset(seed=seed)
    total, steps, done, p = 0.0, 0, False, WaypointPilot()
    dive = np.array([1.0, -1.0, 0.0], dtype=np.float32)  # full thrust tilted down: into the floor
    while not done:
        a = p.act(info["state"], info["goal"]).astype(np.float32) if pilot else dive
        _, r, term, trunc, info = env.step(a)
        total, steps, done = total + r, steps + 1, term or trunc
    return total, info, steps


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_waypoint_flying_the_course_beats_crashing_at_once(seed: int) -> None:
    """The waypoint reward must not make crashing optimal (the earlier ``alive - distance``
    reward did: the pilot's course scored about -236, a dive into the floor about -30)."""
    crash, crash_info, crash_steps = _waypoint_return(seed, pilot=False)
    flown, info, steps = _waypoint_return(seed, pilot=True)
    assert crash_info["crashed"] and crash_steps < 40
    assert not info["crashed"] and steps == gpbf_env.MAX_EPISODE_STEPS  # holds the last waypoint
    assert flown > crash + 100, (flown, crash)
    assert info["success"] and info["waypoint_index"] == 3  # every waypoint reached


def test_waypoint_progress_telescopes_to_the_distance_covered() -> None:
    from agents.pilots import WaypointPilot

    env = gym.make("gpbf_env/BlimpWaypoint-v0", reality="clean")
    _, info = env.reset(seed=3)
    weights = env.unwrapped.config.weights
    pos, goal, pilot = info["state"][:3], info["goal"], WaypointPilot()
    start = float(np.linalg.norm(goal[:3] - pos))
    progress, bonus_steps, done = 0.0, 0, False
    while not done:
        _, r, term, trunc, info = env.step(pilot.act(info["state"], info["goal"]).astype(np.float32))
        done = term or trunc
        progress += info["reward_distance"]
        dense = (
            info["reward_alive"] + info["reward_distance"] + info["reward_heading"] + info["reward_control"]
        )
        bonus_steps += bool(np.isclose(r - dense, weights.reach_bonus))
        if info["waypoint_index"] > 0:  # the first leg ended on this step
            break
    # the first leg's progress sums to progress weight x (start distance - end distance)
    assert progress == pytest.approx(weights.progress * (start - info["distance_m"]), rel=1e-9)
    assert bonus_steps == 1 and info["distance_m"] < weights.reach_radius


def test_kernel_cache_prunes_only_its_own_folder(tmp_path) -> None:
    """Stale ``numba-*`` caches are removed from the package's ``__pycache__``, never from
    the temporary folder that installs of other versions share."""
    from gpbf_env.jit import _cache_dir

    home, shared = tmp_path / "pkg" / "__pycache__", tmp_path / "shared"
    (home / "numba-old").mkdir(parents=True)
    (shared / "numba-other").mkdir(parents=True)
    assert _cache_dir(home, shared, "numba-new") == home / "numba-new"
    assert not (home / "numba-old").exists() and (shared / "numba-other").exists()
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    assert _cache_dir(blocked / "__pycache__", shared, "numba-new") == shared / "numba-new"
    assert (shared / "numba-other").exists()
    assert _cache_dir(blocked / "x", blocked / "y", "numba-new") is None
