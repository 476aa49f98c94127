"""The estimator as a library: system descriptions, logs, the model store, atomic files,
short reprs, and one filter interface."""

from __future__ import annotations

import json
import math
import os
import re
import stat
from pathlib import Path

import numpy as np
import pytest

from estimator_service.blimp import blimp_system
from estimator_service.files import atomic_write_text, remove_stale_temps
from estimator_service.filters import EKF, PF, UKF, GaussianBelief
from estimator_service.flight import FlightError, load_csv, load_log, make_flight, save_flight
from estimator_service.models import LinearGaussianObservation, LinearGaussianPrediction
from estimator_service.store import ModelStoreError, check_folder, model_version, seal, writing
from estimator_service.system import DescriptionError, System
from tests.hostile_files import npz_declaring
from tests.robot_log import SYSTEM, write_robot_log

ROOT = Path(__file__).resolve().parents[1]


def test_system_round_trips_and_errors_name_the_field() -> None:
    s = System.from_dict(SYSTEM)
    assert System.from_json(s.to_json()) == s
    assert s.obs_dim == 3 and s.sensor_slice(1) == slice(2, 3) and s.circle_inputs == (2,)
    z, valid = s.frames({1: [0.5]})
    assert valid.tolist() == [False, False, True] and z[2] == 0.5
    np.testing.assert_allclose(s.state_error(np.array([0, 0, 3.1, 0, 0]), np.array([0, 0, -3.1, 0, 0]))[2],
                               6.2 - 2 * math.pi)  # fmt: skip
    for bad, field in ((dict(SYSTEM, dt=0), "dt"), (dict(SYSTEM, state_periods=[0, 1]), "state_periods"),
                       ({k: v for k, v in SYSTEM.items() if k != "sensors"}, "sensors")):  # fmt: skip
        with pytest.raises(DescriptionError, match=field):
            System.from_dict(bad)
    assert "Cholesky" not in repr(s) and len(repr(s)) < 200


def test_blimp_description_matches_the_filters_angle_handling() -> None:
    w = blimp_system(2).wrapping()
    assert w.state.tolist() == [0] * 3 + [2 * math.pi] * 3 + [0] * 6
    assert w.obs.tolist() == [0, 0, 0, 0, math.pi] * 2


def test_disturbed_states_round_trip_default_to_all_and_bad_ones_are_named() -> None:
    """The blimp names its body velocities; a description without the field (every log
    written before it) means all states and equals one with it (a filter setting)."""
    blimp = blimp_system(2)
    assert blimp.disturbed == (6, 7, 8, 9, 10, 11)
    assert System.from_json(blimp.to_json()).disturbed == blimp.disturbed
    plain = System.from_dict(SYSTEM)
    assert plain.disturbed is None and json.loads(plain.to_json())["disturbed"] is None
    assert System.from_dict(dict(SYSTEM, disturbed=[3, 4])) == plain
    for bad in ([5], [-1], [1, 1], [], "v", [1.5], 3):
        with pytest.raises(DescriptionError, match=r"disturbed|malformed"):
            System.from_dict(dict(SYSTEM, disturbed=bad))


def test_csv_log_reads_and_mistakes_are_named(tmp_path: Path) -> None:
    log, sys_file = write_robot_log(tmp_path, np.random.default_rng(1), rows=50)
    system = System.from_json(sys_file.read_text())
    fl = load_csv(log, system)
    assert len(fl) == 50 and fl.valid[:, 0].sum() == 5 and fl.valid[:, 1].all()
    back = load_log(save_flight(fl, tmp_path / "f.npz"))
    np.testing.assert_array_equal(back.z, fl.z)
    text = log.read_text().splitlines()
    (tmp_path / "bad.csv").write_text("\n".join([text[0], text[1].replace(",", ",x", 1), *text[2:]]))
    with pytest.raises(FlightError, match=r"line 2.*not a number"):
        load_csv(tmp_path / "bad.csv", system)
    (tmp_path / "cols.csv").write_text("\n".join(line.rsplit(",", 1)[0] for line in text))
    with pytest.raises(FlightError, match=r"missing column.*compass\.heading"):
        load_csv(tmp_path / "cols.csv", system)
    with pytest.raises(FlightError, match="--system"):
        load_log(log)


def test_written_files_follow_the_umask_and_failed_writes_leave_nothing(tmp_path: Path) -> None:
    old = os.umask(0o027)
    try:
        p = atomic_write_text(tmp_path / "a.txt", "x")
    finally:
        os.umask(old)
    assert stat.S_IMODE(p.stat().st_mode) == 0o640

    def boom(fh):
        fh.write(b"partial")
        raise RuntimeError("disk on fire")

    from estimator_service.files import atomic_write

    with pytest.raises(RuntimeError):
        atomic_write(tmp_path / "b.bin", boom)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.txt"]
    killed = tmp_path / ".gpbf-killed.tmp"
    killed.write_bytes(b"left by SIGKILL")
    atomic_write_text(tmp_path / "c.txt", "y")  # a fresh one may belong to a live writer
    assert killed.exists()
    os.utime(killed, (0, 0))  # an hour and more old: its writer is dead
    atomic_write_text(tmp_path / "c.txt", "z")
    assert not killed.exists()
    killed.write_bytes(b"again")
    assert remove_stale_temps(tmp_path) == 1


def test_a_failed_write_names_the_destination_not_the_temporary_file(tmp_path: Path) -> None:
    """The operating system's error for a folder where the file should go (or a full disk)
    names the path the user gave, keeps its type and errno, and leaves no temporary file."""
    import errno

    from estimator_service.files import atomic_write

    (tmp_path / "out").mkdir()
    with pytest.raises(IsADirectoryError) as err:
        atomic_write_text(tmp_path / "out", "x")
    assert err.value.filename == str(tmp_path / "out") and ".gpbf-" not in str(err.value)

    def full(fh):
        raise OSError(errno.ENOSPC, "No space left on device", fh.name)

    with pytest.raises(OSError, match=r"No space left on device: '.*b\.bin'") as err:
        atomic_write(tmp_path / "b.bin", full)
    assert err.value.errno == errno.ENOSPC and ".gpbf-" not in str(err.value)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["out"]


def test_model_folder_is_replaced_whole_or_not_at_all(tmp_path: Path) -> None:
    system = blimp_system(1)
    out = tmp_path / "models"
    with writing(out, system) as stage:
        (stage / "prediction_gp.npz").write_bytes(b"old")
    v1 = model_version(out)
    with pytest.raises(RuntimeError), writing(out, system) as stage:
        (stage / "prediction_gp.npz").write_bytes(b"new, half written")
        raise RuntimeError("killed mid-train")
    assert (out / "prediction_gp.npz").read_bytes() == b"old" and model_version(out) == v1
    assert [p.name for p in tmp_path.iterdir()] == ["models"]  # no staging folder left
    killed, running = tmp_path / ".models.staging-killed", tmp_path / ".models.staging-running"
    killed.mkdir()
    running.mkdir()
    os.utime(killed, (0, 0))  # a training killed an hour and more ago
    with writing(out, system) as stage:
        (stage / "prediction_gp.npz").write_bytes(b"old")
    assert not killed.exists() and running.exists()  # a young one may be a training still running
    running.rmdir()
    (out / "prediction_egp.npz").write_bytes(b"stray")  # a mixed folder
    with pytest.raises(ModelStoreError, match="not in the manifest"):
        check_folder(out)
    (out / "prediction_egp.npz").unlink()
    (out / "calibration.json").write_text('{"noise_scale": {"gp": 100.0}}')  # scales added after sealing
    with pytest.raises(ModelStoreError, match=r"not in the manifest \['calibration.json'\]"):
        check_folder(out)
    (out / "calibration.json").unlink()
    (out / "prediction_gp.npz").write_bytes(b"changed")
    with pytest.raises(ModelStoreError, match="differs"):
        check_folder(out)
    seal(out, system)
    assert model_version(out) != v1
    assert json.loads((out / "system.json").read_text())["name"] == "blimp"


def _linear_filters():
    pred = LinearGaussianPrediction(np.eye(2), np.ones((2, 1)), np.full(2, 0.01))
    obs = LinearGaussianObservation(np.eye(2), np.full(2, 0.1))
    return EKF(pred, obs), UKF(pred, obs), PF(pred, obs, n_particles=400)


@pytest.mark.parametrize("filt", _linear_filters(), ids=["EKF", "UKF", "PF"])
def test_one_filter_interface(filt) -> None:
    rng = np.random.default_rng(0)
    belief = filt.initial(GaussianBelief(np.zeros(2), np.eye(2)), rng)
    for _ in range(5):
        belief, _ = filt.step(belief, np.array([0.1]), np.array([0.5, 0.5]), np.array([True, True]), rng)
    g = filt.gaussian(belief)
    assert isinstance(g, GaussianBelief) and np.all(np.abs(g.mean - 0.5) < 0.3)
    assert len(repr(filt)) < 400 and len(repr(belief)) < 400


def test_pf_without_rng_is_a_clear_error() -> None:
    pf = _linear_filters()[2]
    with pytest.raises(TypeError, match="rng"):
        pf.initial(GaussianBelief(np.zeros(2), np.eye(2)))


def test_no_caller_branches_on_the_filter_type() -> None:
    pattern = re.compile(r"isinstance\([^)]*\b(PF|EKF|UKF)\b")
    hits = [
        f"{p.relative_to(ROOT)}:{i}"
        for pkg in ("agents", "estimator_service")
        for p in (ROOT / pkg).rglob("*.py")
        for i, line in enumerate(p.read_text().splitlines(), 1)
        if pattern.search(line)
    ]
    assert not hits, hits


def test_make_flight_checks_shapes() -> None:
    s = System.from_dict(SYSTEM)
    with pytest.raises(FlightError, match="'state' has shape"):
        make_flight(s, np.arange(3.0), np.zeros((3, 4)), np.zeros((3, 2)), np.zeros((3, 3)), np.ones((3, 2)))


def test_hostile_model_and_flight_files_are_refused_by_name(tmp_path: Path) -> None:
    """A model file edited in place at the same size is refused on load (every file's hash is
    checked, not only on request); NaN hyperparameters, a ``__format__`` that is not one
    integer, and an array declaring terabytes (models and flights) are one-line errors, read
    at no cost (were: silent wrong beliefs, NaN at every step, tracebacks, MemoryError)."""
    from estimator_service.factory import build_filter
    from estimator_service.flight import load_flight
    from estimator_service.gp.io import ModelFileError, load_gp
    from estimator_service.training import TrainSettings, train_models

    log, sys_file = write_robot_log(tmp_path, np.random.default_rng(1), rows=200)
    system = System.from_json(sys_file.read_text())
    flight = load_csv(log, system)
    out = tmp_path / "m"
    train_models([flight], out, kinds=["gp"], settings=TrainSettings(n_points=30, calibration_seconds=0))
    build_filter("ekf", "gp", out)
    path = out / "prediction_gp.npz"
    with np.load(path) as d:
        arrays = {k: d[k] for k in d.files}
    size = path.stat().st_size
    key = next(k for k, v in arrays.items() if v.dtype == np.float64 and v.ndim == 2)
    np.savez(path, **{**arrays, key: arrays[key] * 3.0})  # the same-size edit
    assert path.stat().st_size == size
    with pytest.raises(ModelStoreError, match=r"prediction_gp\.npz is missing or differs"):
        build_filter("ekf", "gp", out)
    with pytest.raises(ModelStoreError, match="differs"):
        model_version(out)
    theta = next(k for k in arrays if k.endswith("theta"))
    nan = {**arrays, theta: np.full_like(arrays[theta], np.nan)}
    np.savez(tmp_path / "nan.npz", **nan)
    with pytest.raises(ModelFileError, match=f"'{theta}' holds NaN"):
        load_gp(tmp_path / "nan.npz")
    np.savez(tmp_path / "fmt.npz", **{**arrays, "__format__": np.array([1, 2])})
    with pytest.raises(ModelFileError, match="'__format__' must be one integer"):
        load_gp(tmp_path / "fmt.npz")
    npz_declaring(tmp_path / "huge.npz", "theta", (10**12,), {"__format__": np.array(1)})
    with pytest.raises(ModelFileError, match="declares 8000000000000 bytes"):
        load_gp(tmp_path / "huge.npz")
    npz_declaring(tmp_path / "huge_flight.npz", "state", (10**11, 5))
    with pytest.raises(FlightError, match="array 'state' declares"):
        load_flight(tmp_path / "huge_flight.npz")


def test_hostile_flight_files_are_one_line_errors(tmp_path: Path) -> None:
    """A scalar ``t``, a flight without rows and NaN episode numbers are refused by name
    (were: a TypeError traceback, a later failure, and NaN cast to an arbitrary episode)."""
    from estimator_service.flight import load_flight

    log, sys_file = write_robot_log(tmp_path, np.random.default_rng(2), rows=20)
    good = tmp_path / "good.npz"
    save_flight(load_csv(log, System.from_json(sys_file.read_text())), good)
    with np.load(good) as d:
        arrays = {k: d[k] for k in d.files}
    for name, change, needle in (
        ("scalar_t", {"t": np.array(1.0)}, "'t' must be a 1-D array with at least one row, got shape ()"),
        (
            "no_rows",
            {k: v[:0] for k, v in arrays.items() if k != "metadata"},
            "at least one row, got shape (0,)",
        ),
        (
            "nan_episode",
            {"episode": np.where(np.arange(20) == 3, np.nan, 0.0)},
            "'episode' must hold whole numbers",
        ),
        ("half_episode", {"episode": np.full(20, 0.5)}, "'episode' must hold whole numbers"),
    ):
        path = tmp_path / f"{name}.npz"
        np.savez(path, **{**arrays, **change})
        with pytest.raises(FlightError, match=re.escape(needle)):
            load_flight(path)
    assert len(load_flight(good)) == 20
