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
