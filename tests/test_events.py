"""Asynchronous event logs aligned to filter steps, extra readings within a step, ROS bags."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from estimator_service.events import EventLog, align, load_event_csv
from estimator_service.filters import EKF, UKF
from estimator_service.flight import FlightError, load_flight, save_flight
from estimator_service.models import LinearGaussianObservation, LinearGaussianPrediction
from estimator_service.system import System
from estimator_service.tracking import track_flight
from tests.test_filters import DT, A, B, H, Q, R

TWO_PI = 2 * math.pi
TOY = System.from_dict(
    {
        "name": "toy",
        "state": ["x", "heading"],
        "state_periods": [0, TWO_PI],
        "controls": ["v"],
        "sensors": [{"name": "beacon", "outputs": ["r"]}, {"name": "other", "outputs": ["a", "b"]}],
        "dt": 0.125,
    }
)


def _wrap(a):
    return (np.asarray(a) + math.pi) % TWO_PI - math.pi


def _worked_log() -> EventLog:
    """Ground truth every 1/32 s on [0, 0.5] and [0.8125, 1] (a gap), heading crossing +-pi;
    commands j = 0..31 at j/32 s with value j; beacon readings at chosen times."""
    ts = np.concatenate([np.arange(0, 17) / 32, np.arange(26, 33) / 32])
    state = np.stack([ts, _wrap(3.0 + ts)], axis=1)
    j = np.arange(32)
    beacon_t = [0.26, 0.30, 0.5, 0.1, 2.0, 0.6]
    return EventLog.from_streams(
        TOY,
        {
            "state": (ts, state),
            "control": (j / 32, j[:, None]),
            "beacon": (beacon_t, np.arange(1.0, 7.0)[:, None]),
            "other": ([0.75 + 1 / 64], [[7.0, 8.0]]),
        },
    )


def test_alignment_follows_the_documented_rule_on_a_worked_example() -> None:
    flight, report = align(_worked_log(), control_delay=0.25, max_gap=0.2)
    # rows at 0.25 + 0.125 k up to 1.0; those at 0.625 and 0.75 lie in the gap (0.5, 0.8125)
    np.testing.assert_array_equal(flight.t, [0.25, 0.375, 0.5, 0.875, 1.0])
    np.testing.assert_array_equal(flight.episode, [0, 0, 0, 1, 1])
    assert (report.rows, report.rows_dropped, report.episodes) == (5, 2, 2)
    np.testing.assert_allclose(flight.state[:, 0], flight.t, atol=1e-12)
    np.testing.assert_allclose(_wrap(flight.state[:, 1] - (3.0 + flight.t)), 0, atol=1e-12)  # on the circle
    # row k at 0.25 + k/8: commands sent in [k/8, k/8 + 1/8) act within it: j = 4k..4k+3, mean 4k + 1.5
    k = np.array([0, 1, 2, 5, 6])
    np.testing.assert_allclose(flight.control[:, 0], 4 * k + 1.5)
    held, _ = align(_worked_log(), control="hold", control_delay=0.25, max_gap=0.2)
    np.testing.assert_allclose(held.control[:, 0], 4 * k)  # the last command acting at t_k
    # beacon: 0.26 and 0.30 -> row 0 (first, then extra), 0.5 -> row 2, 0.1 and 2.0 outside,
    # 0.6 -> the dropped row at 0.625; other: 0.765625 -> dropped row 0.75
    np.testing.assert_array_equal(flight.valid[:, 0], [True, False, True, False, False])
    assert flight.z[0, 0] == 1.0 and flight.z[2, 0] == 3.0
    assert flight.extra is not None
    np.testing.assert_array_equal(flight.extra.row, [0])
    assert flight.extra.z[0, 0] == 2.0 and flight.extra.valid[0].tolist() == [True, False]
    assert report.first == {"beacon": 2, "other": 0}
    assert report.extra == {"beacon": 1, "other": 0}
    assert report.dropped == {"beacon": 3, "other": 1}
    states, values = flight.readings(0)  # training sees every reading, each with its row's state
    np.testing.assert_allclose(values[:, 0], [1.0, 3.0, 2.0])
    np.testing.assert_allclose(states[:, 0], [0.25, 0.5, 0.25])


def test_extra_readings_survive_save_select_and_dropping_rows(tmp_path: Path) -> None:
    flight, _ = align(_worked_log(), control_delay=0.25, max_gap=0.2)
    back = load_flight(save_flight(flight, tmp_path / "f.npz"))
    np.testing.assert_array_equal(back.extra.row, flight.extra.row)
    np.testing.assert_array_equal(back.extra.z, flight.extra.z)
    assert flight.select(np.array([1, 2])).extra is None
    moved = flight.select(np.array([0, 2]))
    np.testing.assert_array_equal(moved.extra.row, [0])
    assert flight.without_readings(slice(0, 1)).extra is None
    assert flight.without_readings(slice(1, 3)).extra is not None


def test_event_csv_reader_and_its_errors(tmp_path: Path) -> None:
    path = tmp_path / "events.csv"
    path.write_text(
        "t,stream,v1,v2\n# a comment\n0.0,state,0,0\n0.5,state,0.5,0.1\n1.0,state,1.0,0.2\n"
        "0.0,control,1,\n0.3,beacon,2.5\n0.31,beacon,2.6\n0.4,other,1,2\n"
    )
    flight, report = align(load_event_csv(path, TOY))
    assert len(flight) == 9 and report.first == {"beacon": 1, "other": 1} and report.extra["beacon"] == 1
    bad = {
        "0.1,wheel,1\n": "stream 'wheel' is none of",
        "0.1,beacon,1,2\n": "'beacon' takes 1 values, got 2",
        "x,beacon,1\n": "line 2: not a number",
    }
    for line, message in bad.items():
        path.write_text("t,stream,v\n" + line)
        with pytest.raises(FlightError, match=message):
            load_event_csv(path, TOY)
    with pytest.raises(FlightError, match="no 'control' stream"):
        path.write_text("0,state,0,0\n1,state,1,1\n")
        load_event_csv(path, TOY)
    with pytest.raises(FlightError, match="control_delay must be >= 0"):
        align(_worked_log(), control_delay=-0.1)
    with pytest.raises(FlightError, match=r"stream 'beacon': times \(N,\) and values \(N, 1\)"):
        EventLog.from_streams(TOY, {"state": ([0, 1], [[0, 0], [1, 1]]), "control": ([0], [[1]]),
                                    "beacon": ([0, 1, 2], [[1], [2]])})  # fmt: skip
    with pytest.raises(FlightError, match=r"unknown stream\(s\) \['wheel'\]"):
        EventLog.from_streams(TOY, {"state": ([0], [[0, 0]]), "control": ([0], [[1]]), "wheel": ([0], [[1]])})


# A linear-Gaussian robot (the filter tests' A, B, Q, H, R): extra readings within a step
# must update like independent readings in a joint Kalman update.
LINEAR = System.from_dict(
    {
        "name": "linear",
        "state": ["x", "y", "vx", "vy"],
        "controls": ["ax", "ay"],
        "sensors": [{"name": "pos", "outputs": ["x", "y"]}, {"name": "sum", "outputs": ["s"]}],
        "dt": DT,
    }
)


@pytest.mark.parametrize("cls", [EKF, UKF])
def test_extra_readings_update_as_a_joint_kalman_update(cls) -> None:
    rng = np.random.default_rng(3)
    steps = 40
    x = np.zeros((steps, 4))
    u = rng.normal(size=(steps, 2))
    for k in range(steps - 1):
        x[k + 1] = A @ x[k] + B @ u[k] + rng.normal(size=4) * np.sqrt(Q)
    pos = lambda k: H[:2] @ x[k] + rng.normal(size=2) * np.sqrt(R[:2])  # noqa: E731
    streams = {
        "state": (np.arange(steps) * DT, x),
        "control": (np.arange(steps) * DT, u),
        "pos": ([], np.zeros((0, 2))),
        "sum": (
            np.arange(1, steps) * DT,
            [H[2] @ x[k] + rng.normal() * math.sqrt(R[2]) for k in range(1, steps)],
        ),
    }
    times, values = [], []
    for k in range(1, steps):  # one or two position fixes per step, within 0.05 s of it
        for extra in range(1 + k % 2):
            times.append(k * DT - 0.05 + 0.03 * extra)
            values.append(pos(k))
    streams["pos"] = (times, values)
    flight, report = align(EventLog.from_streams(LINEAR, streams), control="hold")
    assert report.extra["pos"] == steps // 2
    init = np.array([0.2, 0.2, 0.1, 0.1])
    result = track_flight(cls(LinearGaussianPrediction(A, B, Q), LinearGaussianObservation(H, R)), flight,
                          init_std=init)  # fmt: skip
    mean, cov = x[0].copy(), np.diag(init**2)
    for k in range(steps - 1):
        mean, cov = A @ mean + B @ u[k], A @ cov @ A.T + np.diag(Q)
        rows = [flight.z[k + 1, :2], flight.z[k + 1, 2:]]
        hs, rs = [H[:2], H[2:]], [R[:2], R[2:]]
        for i in flight.extra.at(k + 1):
            rows.append(flight.extra.z[i, :2])
            hs.append(H[:2])
            rs.append(R[:2])
        h, r, z = np.concatenate(hs), np.diag(np.concatenate(rs)), np.concatenate(rows)
        s = h @ cov @ h.T + r
        gain = cov @ h.T @ np.linalg.inv(s)
        mean, cov = mean + gain @ (z - h @ mean), (np.eye(4) - gain @ h) @ cov
        np.testing.assert_allclose(result.mean[k], mean, atol=1e-9)
        np.testing.assert_allclose(result.cov[k], cov, atol=1e-9)
        assert result.dof[k] == len(z)


UNICYCLE = {
    "name": "unicycle",
    "state": ["x", "y", "heading"],
    "state_periods": [0, 0, TWO_PI],
    "controls": ["v", "w"],
    "sensors": [
        {"name": "gps", "outputs": ["x", "y"]},
        {"name": "compass", "outputs": ["h"], "periods": [TWO_PI]},
    ],
    "dt": 0.1,
}


def _drive(seconds: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground truth at 100 Hz of a unicycle under smooth commands: times, states, commands."""
    t = np.arange(0, seconds, 0.01)
    u = np.stack([0.4 + 0.2 * np.sin(0.3 * t), 0.6 * np.sin(0.17 * t + 1.0)], axis=1)
    x = np.zeros((len(t), 3))
    for k in range(len(t) - 1):
        px, py, h = x[k]
        x[k + 1] = [
            px + u[k, 0] * math.cos(h) * 0.01,
            py + u[k, 0] * math.sin(h) * 0.01,
            _wrap(h + u[k, 1] * 0.01),
        ]
    return t, x, u + 0.01 * rng.standard_normal(u.shape)


def test_a_rosbag2_mcap_log_trains_and_tracks(tmp_path: Path) -> None:
    """A unicycle's run written as a rosbag2 with MCAP storage by rosbags: ground truth as
    Pose2D at 50 Hz, commands as Twist at 100 Hz, GPS fixes as PointStamped at 2 Hz (logged
    0.2 s late: the header's stamp counts) on one topic with the sensor in frame_id, a
    compass as Float64 at 10 Hz; read, aligned, trained and tracked."""
    pytest.importorskip("rosbags")
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from estimator_service.factory import build_filter
    from estimator_service.rosbag import load_rosbag
    from estimator_service.training import TrainSettings, train_models

    rng = np.random.default_rng(0)
    ts = get_typestore(Stores.LATEST)
    msg = lambda name: ts.types[name]  # noqa: E731
    pose, twist, vec = (
        msg("geometry_msgs/msg/Pose2D"),
        msg("geometry_msgs/msg/Twist"),
        msg("geometry_msgs/msg/Vector3"),
    )
    stamped, point = msg("geometry_msgs/msg/PointStamped"), msg("geometry_msgs/msg/Point")
    header, stamp, number = (
        msg("std_msgs/msg/Header"),
        msg("builtin_interfaces/msg/Time"),
        msg("std_msgs/msg/Float64"),
    )
    t, x, u = _drive(60.0, rng)
    ns = lambda s: round(s * 1e9)  # noqa: E731
    bag = tmp_path / "run"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = {
            topic: w.add_connection(topic, kind.__msgtype__, typestore=ts)
            for topic, kind in [("/mocap", pose), ("/cmd", twist), ("/fixes", stamped), ("/compass", number)]
        }

        def put(topic: str, at: float, m) -> None:
            w.write(conn[topic], ns(at), ts.serialize_cdr(m, m.__msgtype__))

        for k in range(len(t)):
            if k % 2 == 0:
                put("/mocap", t[k], pose(x=x[k, 0], y=x[k, 1], theta=x[k, 2]))
            put(
                "/cmd", t[k], twist(linear=vec(x=u[k, 0], y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=u[k, 1]))
            )
            if k % 10 == 3:
                put("/compass", t[k], number(data=float(_wrap(x[k, 2] + 0.02 * rng.standard_normal()))))
            if k % 50 == 0:
                fix = x[k, :2] + 0.05 * rng.standard_normal(2)
                head = header(stamp=stamp(sec=ns(t[k]) // 10**9, nanosec=ns(t[k]) % 10**9), frame_id="gps")
                put("/fixes", t[k] + 0.2, stamped(header=head, point=point(x=fix[0], y=fix[1], z=0.0)))
                put("/fixes", t[k] + 0.2, stamped(header=header(stamp=head.stamp, frame_id="other"),
                                                  point=point(x=0.0, y=0.0, z=0.0)))  # fmt: skip
    assert list(bag.glob("*.mcap"))
    system = System.from_dict(UNICYCLE)
    mapping = {
        "streams": {
            "state": {"topic": "/mocap", "fields": ["x", "y", "theta"]},
            "control": {"topic": "/cmd", "fields": ["linear.x", "angular.z"]},
            "gps": {"topic": "/fixes", "fields": ["point.x", "point.y"], "where": {"header.frame_id": "gps"}},
            "compass": {"topic": "/compass", "fields": ["data"]},
        }
    }
    log = load_rosbag(bag, system, mapping)
    assert (len(log.state), len(log.control), len(log.readings[0]), len(log.readings[1])) == (
        3000,
        6000,
        120,
        600,
    )
    np.testing.assert_allclose(log.readings[0].t, t[::50], atol=1e-9)  # header stamps, not the logging time
    flight, report = align(log)
    assert report.first == {"gps": 120, "compass": 600} and report.dropped["gps"] == 0
    out = tmp_path / "models"
    settings = TrainSettings(n_points=150, restarts=0, max_iter=30, calibration_seconds=0)
    train_models([flight], out, kinds=["gp"], settings=settings)
    scores = track_flight(build_filter("ekf", "gp", out), flight).scores()
    assert scores["nees"] < 30
    with pytest.raises(FlightError, match="stream 'gps': no topic '/nowhere'"):
        load_rosbag(
            bag, system, {"streams": {**mapping["streams"], "gps": {"topic": "/nowhere", "fields": ["x"]}}}
        )
    with pytest.raises(FlightError, match=r"has no field 'point\.w'"):
        bad = {**mapping["streams"]["gps"], "fields": ["point.x", "point.w"]}
        load_rosbag(bag, system, {"streams": {**mapping["streams"], "gps": bad}})


@pytest.mark.parametrize("slice_s", [0.02, 1e-9])  # 1e-9: the catch-up continues over 4 worker turns
@pytest.mark.parametrize(("delay", "expected"), [(0.25, 0.25), (0.0, 1.0)])
def test_the_service_applies_the_declared_control_delay_to_controls_at_their_own_times(
    delay, expected, slice_s
) -> None:
    """A service session taking controls and frames at their own times acts on a command
    ``control_delay`` after it was sent, as aligning an event log does: p' = p + u dt with
    dt 1/8 s, delay 1/4 s, u = 1 sent at 0 and u = 3 at 1/4; a frame at 1/2 s (observation
    noise 1e8, so the belief is the prediction) finds p = (0 + 0 + 1 + 1) / 8 = 0.25 (without
    the delay: (1 + 1 + 3 + 3) / 8 = 1)."""
    import time

    from estimator_service.service.limits import Limits
    from estimator_service.service.protocol import PROTOCOL_VERSION as V
    from estimator_service.service.protocol import decode, encode
    from estimator_service.service.session import Session, SessionSettings

    sensors = [{"name": "pos", "outputs": ["p"]}]
    cart = {"name": "cart", "state": ["p"], "controls": ["u"], "sensors": sensors, "dt": 0.125}
    system = System.from_dict({**cart, "control_delay": delay})
    filt = EKF(LinearGaussianPrediction(np.eye(1), np.full((1, 1), 0.125), np.full(1, 1e-12)),
               LinearGaussianObservation(np.eye(1), np.full(1, 1e8)))  # fmt: skip
    published: list = []
    settings = SessionSettings(system, Limits(catch_up_slice_s=slice_s))
    s = Session("cart", "ekf", "gp", settings, lambda *_: filt,
                lambda kind, p: published.append((kind, decode(p))))  # fmt: skip
    s.submit("reset", encode({"v": V, "seq": 1, "t": 0.0, "mean": [0.0], "std": [1.0]}))
    s.submit("control", encode({"v": V, "seq": 2, "t": 0.0, "u": [1.0]}))
    s.submit("control", encode({"v": V, "seq": 3, "t": 0.25, "u": [3.0]}))
    s.submit("camera", encode({"v": V, "seq": 4, "t": 0.5, "ellipse": [0.0]}), extra=0)
    deadline = time.time() + 5
    while len(published) < 2 and time.time() < deadline:
        time.sleep(0.01)
    s.stop()
    assert published[-1][0] == "belief", published
    mean = np.frombuffer(published[-1][1]["mean"], "<f8")  # beliefs travel as float64 bytes
    assert mean[0] == pytest.approx(expected, abs=1e-6)
