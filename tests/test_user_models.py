"""A robot's own parametric models (named by import path), sensor types shared across
sensors with per-sensor constants, and noise floors: the estimator gives any robot every
model kind the blimp has."""

from __future__ import annotations

import json
import math
import textwrap
from pathlib import Path

import numpy as np
import pytest

from estimator_service.factory import build_filter, load_models
from estimator_service.flight import Flight, make_flight
from estimator_service.models.gp_models import SharedGPObservation, StackedObservationModel
from estimator_service.system import DescriptionError, System
from estimator_service.tracking import track_flight
from estimator_service.training import TrainSettings, available_kinds, train_models
from estimator_service.user_models import UserModelError, load_user_models, resolve

LANDMARKS = ((3.0, 0.0), (0.0, 3.0), (-3.0, 0.0), (0.0, -3.0), (2.0, 2.0))
TRUE = {"k_v": 0.9, "k_w": 1.1, "bias": 0.05}  # the robot's real gains and range bias
FLOOR = (0.05, 0.01)  # the sensor's noise floor: range m, bearing rad
HIGH_FLOOR, HIGH_PROCESS_FLOOR = (0.08, 0.03), 0.01  # above the real noise: the floors bind
SETTINGS = TrainSettings(n_points=150, restarts=1, max_iter=30, sparse_iter=40, calibration_seconds=0)

MODULE = """
import numpy as np

def unicycle(x, u, p, dt):
    v, w, h = p["k_v"] * u[:, 0], p["k_w"] * u[:, 1], x[:, 2]
    return np.stack([x[:, 0] + v * np.cos(h) * dt, x[:, 1] + v * np.sin(h) * dt, h + w * dt], axis=1)

def range_bearing(x, c, p):
    dx, dy = c["lx"] - x[:, 0], c["ly"] - x[:, 1]
    b = np.arctan2(dy, dx) - x[:, 2]
    return np.stack([np.hypot(dx, dy) + p["bias"], (b + np.pi) % (2 * np.pi) - np.pi], axis=1)

def broken(x, c, p):
    return x[:, :1]

def speed_noise(x, u, p, dt):
    pos = np.abs(u[:, 0]) * dt + 0.001
    return np.stack([pos, pos, np.abs(u[:, 1]) * dt + 0.001], axis=1)

def no_noise(x, u, p, dt):
    return np.zeros_like(x)
"""


def description(module: str = "rover_model") -> dict:
    """A unicycle with range-bearing readings of five surveyed landmarks, one sensor type."""
    return {
        "name": "rover",
        "state": ["x", "y", "heading"],
        "state_periods": [0, 0, 2 * math.pi],
        "controls": ["v", "w"],
        "dt": 0.1,
        "prediction_model": {"function": f"{module}:unicycle", "params": {"k_v": 1.0, "k_w": 1.0}},
        "sensor_types": [
            {
                "name": "rb",
                "constants": ["lx", "ly"],
                "model": {"function": f"{module}:range_bearing", "params": {"bias": 0.0}},
            }
        ],
        "sensors": [
            {
                "name": f"lm{i}",
                "outputs": ["range", "bearing"],
                "periods": [0, 2 * math.pi],
                "type": "rb",
                "constants": list(lm),
                "noise_floor": list(FLOOR),
            }
            for i, lm in enumerate(LANDMARKS)
        ],
        "process_noise_floor": [0.001, 0.001, 0.001],
    }


@pytest.fixture()
def rover(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """The user's model module importable by name, and the robot's description."""
    (tmp_path / "rover_model.py").write_text(textwrap.dedent(MODULE))
    monkeypatch.syspath_prepend(str(tmp_path))
    return System.from_dict(description())


def drive(system: System, seed: int, steps: int) -> Flight:
    """The 'real' robot: gains and a range bias the model's initial guesses lack, a drift
    the model has not at all, a range error that depends on the heading."""
    rm = resolve("rover_model:unicycle"), resolve("rover_model:range_bearing")
    rng = np.random.default_rng(seed)
    t = np.arange(steps) * system.dt
    u = np.stack([0.5 + 0.3 * np.sin(0.2 * t + seed), 0.6 * np.sin(0.13 * t + 2 * seed)], axis=1)
    x = np.zeros((steps, 3))
    for k in range(steps - 1):
        x[k + 1] = rm[0](x[k : k + 1], u[k : k + 1], TRUE, system.dt)[0]
        x[k + 1] += [0.01 * math.sin(x[k, 2]), 0.0, 0.0] + np.array([2e-3, 2e-3, 3e-3]) * rng.standard_normal(
            3
        )
        x[k + 1, 2] = (x[k + 1, 2] + math.pi) % (2 * math.pi) - math.pi
    z = np.zeros((steps, 2 * len(LANDMARKS)))
    for i, (lx, ly) in enumerate(LANDMARKS):
        c = {"lx": np.full(steps, lx), "ly": np.full(steps, ly)}
        zz = rm[1](x, c, TRUE) + [0.05, 0.02] * rng.standard_normal((steps, 2))
        zz[:, 0] += 0.02 * np.sin(3 * x[:, 2])
        zz[:, 1] = (zz[:, 1] + math.pi) % (2 * math.pi) - math.pi
        z[:, 2 * i : 2 * i + 2] = zz
    return make_flight(system, t, x, u, z, rng.random((steps, len(LANDMARKS))) < 0.3)


def relabel(flight: Flight, system: System) -> Flight:
    """The same log under another description."""
    return make_flight(system, flight.t, flight.state, flight.control, flight.z, flight.valid)


@pytest.fixture()
def trained(rover: System, tmp_path: Path) -> tuple[Path, Flight]:
    out = tmp_path / "models"
    train_models([drive(rover, 1, 1500)], out, settings=SETTINGS)
    return out, drive(rover, 2, 300)


@pytest.mark.slow
def test_a_user_model_by_import_path_trains_and_tracks_every_kind(rover: System, trained) -> None:
    folder, test = trained
    assert rover.has_parametric and available_kinds(rover) == ("param", "gp", "egp", "hetgp", "sparse")
    fitted = load_user_models(folder / "parametric.json", rover)
    assert fitted.prediction.values["k_v"] == pytest.approx(TRUE["k_v"], abs=0.05)
    assert fitted.prediction.values["k_w"] == pytest.approx(TRUE["k_w"], abs=0.05)
    assert fitted.sensor_types["rb"].values["bias"] == pytest.approx(TRUE["bias"], abs=0.01)
    scores = {}
    for kind in available_kinds(rover):
        for filt in ("ekf", "ukf", "pf"):
            options = {"n_particles": 200} if filt == "pf" else {}
            result = track_flight(
                build_filter(filt, kind, folder, **options), test, rng=np.random.default_rng(0)
            )
            assert np.all(np.isfinite(result.mean)), (kind, filt)
            scores[kind, filt] = result.scores()
    # the method's strongest form on this robot: the GP on the model's residual learns the
    # drift the unicycle lacks (x error 1.5 cm against 4 cm when measured) and stays consistent
    for filt in ("ekf", "ukf"):
        egp, param = scores["egp", filt], scores["param", filt]
        assert egp["x"] < 0.6 * param["x"], (filt, egp["x"], param["x"])
        assert 1.0 < egp["nees"] < 6.0, egp["nees"]  # 3 is consistent


def test_sensors_of_one_type_share_one_gp_with_their_constants(rover: System, trained) -> None:
    folder, _ = trained
    names = sorted(p.name for p in folder.glob("observation_gp_*"))
    assert names == ["observation_gp_type-rb.npz"]  # one GP for the five landmarks
    _, obs = load_models(folder, "gp", calibrated=False)
    assert isinstance(obs, StackedObservationModel) and isinstance(obs.parts[0], SharedGPObservation)
    shared = obs.parts[0]
    assert shared.gp.input_dim == 3 + 2  # the state and the landmark's position
    x = np.array([[0.5, -0.2, 0.3], [1.0, 1.0, -2.0]])
    out = obs.observe(x, jac=True)
    for i, lm in enumerate(LANDMARKS):  # each sensor's columns: the GP at [x, its constants]
        direct = shared.gp.predict(np.concatenate([x, np.tile(lm, (2, 1))], axis=1), return_jac=True)
        np.testing.assert_allclose(out.mean[:, 2 * i : 2 * i + 2], direct.mean, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(
            out.jac[:, 2 * i : 2 * i + 2], direct.jac[:, :, :3], rtol=1e-12, atol=1e-12
        )


@pytest.mark.slow
def test_no_model_claims_less_noise_than_the_floors(rover: System, tmp_path: Path) -> None:
    """Floors above the sensor's real noise (range 0.05 m, bearing 0.02 rad) and the process
    noise: every kind's variances sit at or above them, though the models alone claim less."""
    d = description()
    for sensor in d["sensors"]:
        sensor["noise_floor"] = list(HIGH_FLOOR)
    d["process_noise_floor"] = [HIGH_PROCESS_FLOOR] * 3
    system = System.from_dict(d)
    folder = tmp_path / "floored"
    train_models([drive(system, 1, 1500)], folder, settings=SETTINGS)
    x = np.random.default_rng(0).uniform(-2, 2, size=(50, 3))
    u = np.tile([0.5, 0.1], (50, 1))
    obs_floor, below = np.tile(np.square(HIGH_FLOOR), len(LANDMARKS)), []
    for kind in available_kinds(system):
        (raw_pred, raw_obs), (pred, obs) = (
            load_models(folder, kind, calibrated=False),
            load_models(folder, kind),
        )
        assert np.all(obs.observe(x).var >= obs_floor * (1 - 1e-12)), kind
        assert np.all(pred.predict(x, u).var >= HIGH_PROCESS_FLOOR**2 * (1 - 1e-12)), kind
        below.append(np.any(raw_obs.observe(x).var < obs_floor) and np.any(raw_pred.predict(x, u).var < 1e-4))
    assert sum(below) >= 3, below  # the floors bind: the GP kinds alone claim less
    raw = load_user_models(folder / "parametric.json", system)
    assert np.all(raw.sensor_types["rb"].noise_var >= np.square(HIGH_FLOOR))
    assert np.all(raw.prediction.noise_var >= HIGH_PROCESS_FLOOR**2)
    report = json.loads((folder / "noise.json").read_text())  # training reports noise beside floor
    assert set(report) == set(available_kinds(system))
    assert set(report["gp"]) == {"prediction", "type-rb"}
    assert report["gp"]["type-rb"]["bearing"]["floor"] == HIGH_FLOOR[1]
    assert report["egp"]["type-rb"]["bearing"]["std"] < HIGH_FLOOR[1]  # what the GP alone claims
    assert report["param"]["type-rb"]["range"]["std"] >= HIGH_FLOOR[0]


def test_user_model_jacobians_wrap_angle_outputs_at_the_cut(rover: System, trained) -> None:
    folder, _ = trained
    _, obs = load_models(folder, "param", calibrated=False)
    # behind the robot, the bearing of landmark 0 sits at the +-pi cut
    x = np.array([[4.0, 1e-9, 0.0], [4.0, -1e-9, 0.0]])
    jac = obs.observe(x, jac=True).jac[:, 1]  # d bearing / d state of landmark 0
    expected = np.array([0.0, 1.0, -1.0])  # bearing atan2(-y, -1) - heading: d/dy = 1, d/dheading = -1
    np.testing.assert_allclose(jac, np.tile(expected, (2, 1)), atol=1e-5)


SPEED_NOISE = 0.1  # the robot's process noise std per step: SPEED_NOISE * speed_noise(x, u)


def drive_noisy(system: System, seed: int, steps: int) -> Flight:
    """A robot whose process noise grows with its speed, standing still a third of the time."""
    unicycle = resolve("rover_model:unicycle")
    rng = np.random.default_rng(seed)
    t = np.arange(steps) * system.dt
    moving = (np.sin(0.05 * t) > -0.5).astype(float)
    u = np.stack([moving * (0.5 + 0.5 * np.sin(0.3 * t)), moving * 0.8 * np.sin(0.11 * t)], axis=1)
    x = np.zeros((steps, 3))
    for k in range(steps - 1):
        std = SPEED_NOISE * resolve("rover_model:speed_noise")(x[k : k + 1], u[k : k + 1], TRUE, system.dt)[0]
        x[k + 1] = unicycle(x[k : k + 1], u[k : k + 1], TRUE, system.dt)[0] + std * rng.standard_normal(3)
        x[k + 1, 2] = (x[k + 1, 2] + math.pi) % (2 * math.pi) - math.pi
    rb = resolve("rover_model:range_bearing")
    z = np.concatenate(
        [rb(x, {"lx": np.full(steps, lx), "ly": np.full(steps, ly)}, TRUE) for lx, ly in LANDMARKS], axis=1
    )
    return make_flight(system, t, x, u, z, rng.random((steps, len(LANDMARKS))) < 0.3)


def test_a_noise_shape_is_fitted_and_followed_by_the_parametric_noise(rover: System, tmp_path: Path) -> None:
    """A prediction model naming its noise shape: training fits its factor (the robot's
    0.1) and the ``param`` noise follows the shape (a standing robot's predicted noise far
    below a moving one's; constant without the shape); the GP kinds learn theirs from the
    residuals either way; a description whose shape changed after training is refused."""
    d = description()
    d["prediction_model"]["noise"] = "rover_model:speed_noise"
    shaped = System.from_dict(d)
    flight = drive_noisy(shaped, 3, 1200)
    folders = {}
    for name, system in (("shaped", shaped), ("plain", rover)):
        folders[name] = tmp_path / name
        train_models([relabel(flight, system)], folders[name], settings=SETTINGS, kinds=["param", "egp"])
    factor2 = load_user_models(folders["shaped"] / "parametric.json", shaped).prediction.noise_var
    np.testing.assert_allclose(np.sqrt(factor2), SPEED_NOISE, rtol=0.1)
    x = np.zeros((2, 3))
    u = np.array([[0.0, 0.0], [1.0, 0.8]])  # standing, then fast
    shaped_var = load_models(folders["shaped"], "param", calibrated=False)[0].predict(x, u).var
    plain_var = load_models(folders["plain"], "param", calibrated=False)[0].predict(x, u).var
    assert np.all(shaped_var[1] > 20 * shaped_var[0]), shaped_var
    assert np.all(plain_var[1] == plain_var[0]), plain_var
    egp = [load_models(folders[k], "egp", calibrated=False)[0].predict(x, u).var for k in ("shaped", "plain")]
    np.testing.assert_allclose(egp[0], egp[1], rtol=1e-9)
    edited = folders["shaped"] / "system.json"  # the shape removed after training: refused by name
    doc = json.loads(edited.read_text())
    del doc["prediction_model"]["noise"]
    edited.write_text(json.dumps(doc))
    with pytest.raises(UserModelError, match="fitted with noise shape 'rover_model:speed_noise'"):
        load_models(folders["shaped"], "param", calibrated=False, check=False)


def test_a_noise_shape_at_or_below_zero_is_refused_by_name(rover: System, tmp_path: Path) -> None:
    d = description()
    d["prediction_model"]["noise"] = "rover_model:no_noise"
    system = System.from_dict(d)
    with pytest.raises(
        UserModelError, match=r"'rover_model:no_noise' returned a noise standard deviation <= 0"
    ):
        train_models(
            [relabel(drive(rover, 1, 200), system)], tmp_path / "m", settings=SETTINGS, kinds=["param"]
        )


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d["sensors"][0].update(type="camera"), "unknown type 'camera'"),
        (lambda d: d["sensors"][1].update(constants=[1.0]), "sensor 'lm1' needs 2 'constants'"),
        (lambda d: d["sensors"][2].update(noise_floor=[0.1]), "'noise_floor' needs 2"),
        (lambda d: d["sensors"][3].update(outputs=["r", "b"]), "same outputs and periods"),
        (lambda d: d["prediction_model"].update(function="not a path"), "is not 'package.module:attribute'"),
        (
            lambda d: d["prediction_model"].update(params={"k_v": "fast"}),
            "'params' must map names to numbers",
        ),
        (lambda d: d["prediction_model"].update(fixed={"k_v": 1.0}), "both in 'params' and in 'fixed'"),
        (lambda d: d.update(process_noise_floor=[0.1, -1, 0]), "'process_noise_floor' needs 3"),
        (
            lambda d: d["sensor_types"][0]["model"].update(noise="rover_model:speed_noise"),
            "sensor type 'rb': 'noise' shapes the prediction model's noise only",
        ),
        (lambda d: d["prediction_model"].update(noise="a b"), "'a b' is not 'package.module:attribute'"),
    ],
)
def test_a_malformed_description_names_the_field(edit, message: str) -> None:
    d = description()
    edit(d)
    with pytest.raises(DescriptionError, match=message):
        System.from_dict(d)


def test_descriptions_with_models_round_trip_through_json(rover: System) -> None:
    again = System.from_json(rover.to_json())
    assert again == rover and again.sensors[4].constants == (2.0, 2.0)
    assert again.sensor_type("rb").model.params == (("bias", 0.0),)


def test_a_broken_user_model_fails_training_with_its_name(rover: System, tmp_path: Path) -> None:
    flight = drive(rover, 1, 200)
    d = description()
    d["sensor_types"][0]["model"]["function"] = "rover_model:broken"
    broken = System.from_dict(d)
    with pytest.raises(UserModelError, match=r"'rover_model:broken' returned shape \(\d+, 1\), expected"):
        train_models([relabel(flight, broken)], tmp_path / "m", settings=SETTINGS, kinds=["param"])
    d = description()
    d["prediction_model"]["function"] = "no_such_module:f"
    with pytest.raises(UserModelError, match="'no_such_module:f' cannot be loaded: ModuleNotFoundError"):
        train_models(
            [relabel(flight, System.from_dict(d))], tmp_path / "m", settings=SETTINGS, kinds=["param"]
        )
    assert not (tmp_path / "m").exists()  # nothing half-written


def test_a_tampered_parametric_file_is_refused_by_name(rover: System, trained) -> None:
    folder, _ = trained
    path = folder / "parametric.json"
    doc = json.loads(path.read_text())
    doc["prediction"]["values"]["k_v"] = float("nan")
    path.write_text(json.dumps(doc))
    with pytest.raises(UserModelError, match="values must be finite numbers"):
        load_user_models(path, rover)


def test_a_shared_sensor_type_is_its_gp_at_each_sensors_constants() -> None:
    """Each sensor's block of a shared type (outputs side by side, sensor by sensor) is the
    GP's prediction at ``[x, c_s]``: means, variances and the state block of the Jacobian;
    a subset of columns evaluates only its sensors; without variances the block is zero."""
    from estimator_service.gp import ExactGP, Scaler

    rng = np.random.default_rng(2)
    xs, ys = rng.uniform(-2, 2, (30, 4)), rng.normal(size=(30, 2))
    theta = np.log([[0.9, 1.2, 0.7, 1.5, 1.0, 0.1], [1.4, 0.6, 1.1, 0.8, 2.0, 0.3]])
    gp = ExactGP.from_theta(xs, ys, theta, Scaler(np.zeros(4), np.ones(4)), Scaler(np.zeros(2), np.ones(2)))
    consts = np.array([[0.5, -1.0], [1.5, 0.2], [-0.7, 0.9]])
    shared = SharedGPObservation(gp, consts)
    x = rng.uniform(-1, 1, (5, 2))
    out = shared.observe(x, jac=True)
    assert (shared.state_dim, shared.obs_dim) == (2, 6)
    for s, c in enumerate(consts):
        p = gp.predict(np.c_[x, np.tile(c, (5, 1))], return_jac=True)
        cols = slice(2 * s, 2 * s + 2)
        np.testing.assert_allclose(out.mean[:, cols], p.mean, rtol=1e-12)
        np.testing.assert_allclose(out.var[:, cols], p.var, rtol=1e-12)
        np.testing.assert_allclose(out.jac[:, cols], p.jac[:, :, :2], rtol=1e-12)
    some = shared.observe_columns(x, np.array([5, 0]), jac=True)
    np.testing.assert_allclose(some.var, out.var[:, [5, 0]], rtol=1e-12)
    np.testing.assert_allclose(some.jac, out.jac[:, [5, 0]], rtol=1e-12)
    bare = shared.observe(x, var=False)
    np.testing.assert_allclose(bare.mean, out.mean, rtol=1e-12)
    assert bare.jac is None and bare.var.shape == (5, 6) and not bare.var.any()
