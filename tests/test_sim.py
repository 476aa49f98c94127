"""The simulator glue: flights recorded from the env carry what the estimator needs."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from agents.sim import collect_flight
from estimator_service.blimp import blimp_system, measured
from estimator_service.flight import make_flight


def test_randomised_flights_record_and_train_with_the_parameters_flown() -> None:
    fl = collect_flight(20, seed=2, env_kwargs={"randomize": 0.3})
    env = gym.make("gpbf_env/Blimp-v0", randomize=0.3)
    env.reset(seed=2)
    flown = env.unwrapped.params.to_dict()
    assert fl.metadata["params"] == flown == fl.metadata["episode_params"][0]
    assert fl.metadata["base_params"]["mass"] != flown["mass"]  # the bug: base values were stored
    eps = fl.metadata["episode_params"]
    assert len(eps) == fl.episode.max() + 1
    counts = np.bincount(fl.episode[fl.transition_rows()], minlength=len(eps))
    for key in ("mass", "tail_arm"):
        expected = np.average([p[key] for p in eps], weights=counts + 1e-12)
        assert abs(measured([fl], key) - expected) < 1e-12


def test_measured_constants_weight_each_episode_by_its_transitions() -> None:
    n = 10
    episode = np.array([0] * 4 + [1] * 6)
    meta = {"params": {"mass": 1.0}, "episode_params": [{"mass": 1.0}, {"mass": 2.0}]}
    fl = make_flight(blimp_system(1), np.arange(n) * 0.25, np.zeros((n, 12)), np.zeros((n, 3)),
                     np.zeros((n, 5)), np.zeros((n, 1), bool), episode, **meta)  # fmt: skip
    assert abs(measured([fl], "mass") - (3 * 1.0 + 5 * 2.0) / 8) < 1e-9


def test_flights_record_the_motion_capture_state_and_keep_the_exact_one(tmp_path) -> None:
    import dataclasses

    import pytest

    from estimator_service.flight import FlightError, load_flight, save_flight

    fl = collect_flight(20, seed=3)
    assert fl.exact is not None and fl.exact.shape == fl.state.shape
    err = np.abs(fl.state[:, :3] - fl.exact[:, :3])
    assert 0 < err.max() < 0.005  # sub-millimetre marker noise: the state is the measured one
    back = load_flight(save_flight(fl, tmp_path / "f.npz"))
    np.testing.assert_array_equal(back.exact, fl.exact)
    np.testing.assert_array_equal(back.select(np.arange(5)).exact, fl.exact[:5])
    assert load_flight(save_flight(dataclasses.replace(fl, exact=None), tmp_path / "g.npz")).exact is None
    with pytest.raises(FlightError, match="'exact' has shape"):
        dataclasses.replace(fl, exact=fl.exact[:-1])
