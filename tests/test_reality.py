"""The lab world's unmodelled physics (U1-U8, C1), its presets and motion capture."""

from __future__ import annotations

import dataclasses
import math

import gymnasium as gym
import numpy as np
import pytest

import gpbf_env
from gpbf_env import BlimpParams
from gpbf_env.camera import euler_to_matrix, outline_ellipses
from gpbf_env.coeffs import Coeffs, mass_matrix
from gpbf_env.core import WorldConfig, observe
from gpbf_env.dynamics import derivative, make_coeffs, rk4_step
from gpbf_env.lab_dynamics import motor_track, thrust_targets
from gpbf_env.mocap import AUX_DRAWS, PoseTrack, measure
from gpbf_env.reality import lab_effects

ENV_ID = "gpbf_env/Blimp-v0"
CALM = dataclasses.replace(BlimpParams(), gust_std=0.0, buoyancy_ratio=1.0)


def fly(params: BlimpParams, action: list[float], steps: int, reality: str = "lab") -> np.ndarray:
    """States (steps, 12) of a blimp released at rest holding ``action``."""
    env = gym.make(ENV_ID, params=params, reality=reality, max_episode_steps=None)
    env.reset(seed=0, options={"state": [5, 3, 2, 0, 0, 0, 0, 0, 0, 0, 0, 0]})
    a = np.array(action, dtype=np.float32)
    return np.array([env.step(a)[-1]["state"] for _ in range(steps)])


def test_static_thrust_sweep_has_the_dead_band_exponent_and_reverse_ratios() -> None:
    p = BlimpParams()
    lab = make_coeffs([p], 0.25, 4, 1.0).table[0]
    for a in (-1.0, -0.5, -0.05, 0.0, 0.05, 0.3, 0.7, 1.0):
        main, angle, tail = thrust_targets(a * p.max_main_thrust, 0.4, a * p.max_tail_thrust, lab)
        reach = max((abs(a) - p.thrust_dead_band) / (1 - p.thrust_dead_band), 0.0) ** p.thrust_exponent
        back_main, back_tail = (p.reverse_main, p.reverse_tail) if a < 0 else (1.0, 1.0)
        assert main == pytest.approx(math.copysign(reach * back_main * p.max_main_thrust, a), abs=1e-15)
        assert tail == pytest.approx(math.copysign(reach * back_tail * p.max_tail_thrust, a), abs=1e-15)
        assert angle == 0.4
    assert thrust_targets(p.max_main_thrust, 0.0, 0.0, lab)[0] == pytest.approx(p.max_main_thrust)


def test_axial_inflow_cuts_thrust_as_momentum_theory_says() -> None:
    p = dataclasses.replace(CALM, cg_lateral=0.0)
    c = make_coeffs([p], 0.25, 4, 1.0)
    m = mass_matrix(p, lab_effects(p, 1.0))
    thrust = 0.1
    for speed in (0.0, 1.0, 2.0, 4.0, 6.0):
        state = [5, 3, 2, 0, 0, 0, speed, 0, 0, 0, 0, 0]
        on = np.array(derivative(state, (thrust, 0.0, 0.0), (0.0, 0.0, 0.0), c)[6:])
        off = np.array(derivative(state, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), c)[6:])
        force = m @ (on - off)  # generalised force of the fans alone
        assert force[0] == pytest.approx(thrust * max(0.0, 1 - speed / p.inflow_speed), rel=1e-9, abs=1e-15)


def test_fan_imbalance_yaws_a_blimp_with_the_tail_fan_off() -> None:
    p = dataclasses.replace(CALM, cg_lateral=0.0)
    lab, clean = fly(p, [0.6, 0, 0], 40), fly(p, [0.6, 0, 0], 40, "clean")
    assert abs(clean[-1, 5] - clean[0, 5]) < 1e-9
    assert lab[-1, 5] - lab[0, 5] < -0.02  # left fan stronger: a right turn (negative yaw)
    balanced = fly(dataclasses.replace(p, fan_imbalance=0.0), [0.6, 0, 0], 40)
    assert abs(balanced[-1, 5] - balanced[0, 5]) < 1e-6


def test_steady_turn_rolls_the_blimp_outward_by_atan_ur_over_g() -> None:
    p = dataclasses.replace(CALM, tail_drop=0.0, cg_lateral=0.0)
    for reality in ("lab", "clean"):
        s = fly(p, [0.8, 0, 0.6], 200, reality)[-40:]
        u, r, roll = s[:, 6].mean(), s[:, 11].mean(), s[:, 3].mean()
        outward = -math.atan(u * r / p.gravity)  # the gondola swings out of the turn
        assert abs(outward) > 0.005
        if reality == "lab":
            assert roll == pytest.approx(outward, rel=0.15)
        else:
            assert abs(roll) < 0.1 * abs(outward)


def test_tail_fan_below_the_centreline_rolls_the_blimp() -> None:
    p = dataclasses.replace(CALM, cg_lateral=0.0)
    low, level = (
        fly(p, [0, 0, 1.0], 200)[-40:],
        fly(dataclasses.replace(p, tail_drop=0.0), [0, 0, 1.0], 200)[-40:],
    )
    inflow = low[:, 7].mean() - p.tail_arm * low[:, 11].mean()
    tail = p.max_tail_thrust * (1 - inflow / p.inflow_speed)
    expected = p.tail_drop * tail / (p.mass * p.gravity * p.cg_below_cb)
    assert low[:, 3].mean() - level[:, 3].mean() == pytest.approx(expected, rel=0.1)


def _momenta(p: BlimpParams, state: list[float]) -> tuple[np.ndarray, np.ndarray, float]:
    m = mass_matrix(p, lab_effects(p, 1.0))
    nu = np.array(state[6:])
    impulse = m @ nu
    rot = euler_to_matrix(np.array([state[3:6]]))[0]
    linear = rot @ impulse[:3]
    angular = rot @ impulse[3:] + np.cross(np.array(state[:3]), linear)
    return linear, angular, 0.5 * nu @ impulse


def test_rigid_body_with_low_cg_conserves_momentum_and_energy_without_drag() -> None:
    p = dataclasses.replace(
        CALM, gravity=1e-12, added_mass=(0.2, 0.2, 0.2), lin_drag=(0, 0, 0), quad_drag=(0, 0, 0),
        lin_rot_drag=(0, 0, 0), quad_rot_drag=(0, 0, 0), lift_y_uv=0.0, lift_z_uw=0.0,
        moment_n_uv=0.0, moment_m_uw=0.0,
    )  # fmt: skip
    c = make_coeffs([p], 0.25, 8, 1.0)
    state = [5.0, 3.0, 2.0, 0.1, -0.2, 0.3, 0.4, -0.2, 0.1, 0.5, -0.3, 0.8]
    before = _momenta(p, state)
    motors = (0.0, 0.0, 0.0)
    for _ in range(40):
        state, motors, _ = rk4_step(state, motors, np.zeros(3), np.zeros(3), c)
        state = state[:, 0]
    after = _momenta(p, state)
    for a, b in zip(before, after, strict=True):
        np.testing.assert_allclose(b, a, rtol=1e-6, atol=1e-9)
    assert abs(state[3] - 0.1) > 0.05  # the coupling moved it: the check is not vacuous


def test_a_frame_shows_the_blimp_where_it_was_at_exposure() -> None:
    p = dataclasses.replace(CALM, camera_latency=0.25, camera_jitter=0.0)  # latency = one step
    env = gym.make(ENV_ID, params=p, pixel_noise=0.0, max_episode_steps=None)
    env.reset(seed=1, options={"state": [5, 3, 2, 0, 0, 0.3, 0, 0, 0, 0, 0, 0]})
    cfg = dataclasses.replace(env.unwrapped.config, reality="clean")
    previous = env.unwrapped.state
    compared = 0
    for k in range(40):
        obs, *_, info = env.step(np.array([1.0, 0.0, 0.3], dtype=np.float32))
        frames = obs["valid"][None, :].astype(bool)
        if k > 8 and frames.any():
            zero = np.zeros((1, cfg.noise_size - 3))
            then, _ = observe(cfg, previous[None, :], frames, zero)
            now, _ = observe(cfg, info["state"][None, :], frames, zero)
            np.testing.assert_allclose(obs["ellipses"], then[0], atol=1e-3)
            assert np.abs(obs["ellipses"] - now[0]).max() > 0.5  # it moved: latency shows
            compared += 1
        previous = info["state"]
    assert compared >= 5


@pytest.mark.parametrize("vector", [False, True])
def test_strength_zero_is_the_clean_world_bit_for_bit(vector: bool) -> None:
    def run(**kwargs: object) -> list[np.ndarray]:
        rng = np.random.default_rng(3)
        out = []
        if vector:
            env = gym.make_vec(ENV_ID, num_envs=3, max_episode_steps=60, **kwargs)
            obs, info = env.reset(seed=4)
            shape: tuple[int, ...] = (3, 3)
        else:
            env = gym.make(ENV_ID, max_episode_steps=60, **kwargs)
            obs, info = env.reset(seed=4)
            shape = (3,)
        for _ in range(200):
            obs, reward, term, trunc, info = env.step(rng.uniform(-1, 1, shape).astype(np.float32))
            out += [obs["ellipses"], np.asarray(reward), info["state"], info["mocap"]]
            if not vector and (term or trunc):
                obs, info = env.reset()
        return out

    clean = run(reality="clean")
    for got, want in zip(run(reality="drafty", reality_strength=0.0), clean, strict=True):
        np.testing.assert_array_equal(got, want)
    assert not all(np.array_equal(a, b) for a, b in zip(run(reality="drafty"), clean, strict=True))


def test_mocap_noise_and_velocity_lag_match_the_paper_system() -> None:
    env = gym.make(ENV_ID, max_episode_steps=None)
    env.reset(seed=2)
    rng = np.random.default_rng(5)
    truth, meas = [], []
    for k in range(1200):
        a = rng.uniform(-1, 1, 3) if k % 8 == 0 else a  # noqa: F821 - held for 2 s
        *_, info = env.step(a.astype(np.float32))
        truth.append(info["state"])
        meas.append(info["mocap"])
        if k % 200 == 199:
            env.reset()
    truth, meas = np.array(truth), np.array(meas)
    err = meas - truth
    err[:, 3:6] = (err[:, 3:6] + np.pi) % (2 * np.pi) - np.pi
    assert np.std(err[:, :3]) == pytest.approx(0.5e-3, rel=0.15)
    assert np.std(err[:, 3:6]) == pytest.approx(math.radians(0.05), rel=0.15)
    acc = np.gradient(truth[:, 6], 0.25)
    keep = np.abs(np.arange(len(acc)) % 200 - 100) < 95  # away from the resets
    lag = -np.cov(err[keep, 6], acc[keep])[0, 1] / np.var(acc[keep])
    assert 0.025 < lag < 0.07  # the 100 ms slope lags the truth by about 46 ms


def test_presets_through_gymnasium_make_and_bad_settings_name_the_field() -> None:
    for name in ("lab", "clean", "drafty"):
        env = gym.make(ENV_ID, reality=name)
        env.reset(seed=0)
        assert env.unwrapped.config.reality == name
    assert gym.make(ENV_ID).unwrapped.config.reality == "lab"
    assert gym.make(ENV_ID).unwrapped.config.world_params.gust_std == pytest.approx(0.025)
    venv = gym.make_vec(ENV_ID, num_envs=2, reality="clean")
    assert venv.reset(seed=0)[1]["mocap"].shape == (2, 12)
    with pytest.raises(ValueError, match="reality must be one of"):
        WorldConfig(reality="moon")
    for bad in (-0.5, float("nan"), 9.0, "strong"):
        with pytest.raises(ValueError, match="reality_strength"):
            gpbf_env.WorldConfig(reality_strength=bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="thrust_dead_band"):
        BlimpParams(thrust_dead_band=0.7)


def _track(c: Coeffs, motors: tuple[float, ...], target: tuple[float, float, float]) -> np.ndarray:
    """Motor states (2 n_sub + 1, 3) of blimp 0 over a step towards thrust ``target``."""
    out = np.empty((c.half_times.size, 3))
    motor_track(np.array(motors), target, c.decay[0], c.decay_up[0], c.half_times, c.table[0], out)
    return out


def test_fans_spin_up_faster_than_they_spin_down_and_the_servo_slews_at_its_rate() -> None:
    p = BlimpParams()
    c = make_coeffs([p], 0.25, 4, 1.0)
    assert c.lab
    t = c.half_times
    up = _track(c, (0.0, 0.0, 0.0), (0.1, 0.0, 0.0))[:, 0]
    down = _track(c, (0.1, 0.0, 0.0), (0.0, 0.0, 0.0))[:, 0]
    for k, tk in enumerate(t):
        assert up[k] == pytest.approx(0.1 * (1 - math.exp(-tk / p.tau_spinup)), rel=1e-12, abs=1e-15)
        assert down[k] == pytest.approx(0.1 * math.exp(-tk / p.tau_main), rel=1e-12)
    servo = _track(c, (0.0, 0.0, 0.0), (0.0, 1.5, 0.0))[:, 1]
    for k, tk in enumerate(t):  # far from the target the slew rate binds, near it the lag
        lag_only = 1.5 * (1 - math.exp(-tk / p.tau_angle))
        assert servo[k] <= min(p.servo_rate * tk, lag_only) + 1e-12
    assert servo[2] == pytest.approx(p.servo_rate * t[2])  # still slewing after 62.5 ms
    small = _track(c, (0.0, 0.0, 0.0), (0.0, 0.2, 0.0))[:, 1]
    assert small[-1] == pytest.approx(0.2 * (1 - math.exp(-t[-1] / p.tau_angle)))  # a small step: pure lag


def test_forward_thrust_slipstream_pitches_the_nose_down_and_reverse_thrust_does_not() -> None:
    p = dataclasses.replace(CALM, cg_lateral=0.0)
    state = [5, 3, 2, 0, 0, 0, 0, 0, 0, 0, 0, 0]
    m = mass_matrix(p, lab_effects(p, 1.0))
    for thrust, expected in ((0.1, 0.1 * p.fin_slipstream), (-0.1, 0.0)):
        moments = []
        for params in (p, dataclasses.replace(p, fin_slipstream=0.0)):
            c = make_coeffs([params], 0.25, 4, 1.0)
            moments.append((m @ np.array(derivative(state, (thrust, 0.0, 0.0), (0.0, 0.0, 0.0), c)[6:]))[4])
        assert moments[0] - moments[1] == pytest.approx(expected, abs=1e-15)


def test_compiled_kernels_refuse_misshapen_arrays_naming_them() -> None:
    """The kernels do not check bounds: their Python entry points check every shape."""
    c = make_coeffs([BlimpParams(), BlimpParams()], 0.25, 4, 1.0)
    with pytest.raises(ValueError, match="state must have shape"):
        rk4_step(np.zeros((2, 12)), np.zeros((3, 2)), np.zeros((3, 2)), np.zeros((3, 2)), c)
    with pytest.raises(ValueError, match="wind must have shape"):
        rk4_step(np.zeros((12, 2)), np.zeros((3, 2)), np.zeros((3, 2)), np.zeros(3), c)
    with pytest.raises(ValueError, match="one blimp"):
        derivative(np.zeros(12), np.zeros(3), np.zeros(3), c)
    cfg = WorldConfig()
    rot = euler_to_matrix(np.zeros((2, 3)))
    with pytest.raises(ValueError, match="noise_px must have shape"):
        outline_ellipses(cfg.cameras, np.ones((2, 3)), rot, cfg.semi_axes, np.zeros((2, 1, 16, 2)))
    with pytest.raises(ValueError, match="rotation must have shape"):
        outline_ellipses(cfg.cameras, np.ones((3, 3)), rot, cfg.semi_axes)
    track = PoseTrack(2, 4, 0.25, 3)
    with pytest.raises(ValueError, match="noise must have shape"):
        measure(track, np.zeros((1, AUX_DRAWS)))
