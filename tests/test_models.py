"""Parametric blimp models (fitting, Jacobians) and the (filter x model) factory."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from estimator_service.blimp import blimp_system, load_parametric, save_parametric
from estimator_service.factory import (
    FILTER_KINDS,
    MODEL_KINDS,
    build_filter,
)
from estimator_service.filters import PF, GaussianBelief
from estimator_service.gp import fit_enhanced, fit_exact, fit_hetero, fit_sparse, save_gp
from estimator_service.models.blimp import DEFAULT_PARAMS, BlimpODE, fit_blimp_ode, integrate
from estimator_service.models.camera import CameraModel, PinholeCalibration, fit_camera_model
from estimator_service.store import seal


def look_at(pos, target) -> PinholeCalibration:
    pos = np.asarray(pos, float)
    f = np.asarray(target, float) - pos
    f /= np.linalg.norm(f)
    r = np.cross(f, [0, 0, 1.0])
    r /= np.linalg.norm(r)
    return PinholeCalibration(pos, np.stack([r, np.cross(f, r), f]), 380.0, (319.5, 239.5))


CAMS = (look_at([0.05, 0.05, 3.9], [5, 3, 1.6]), look_at([9.95, 5.95, 3.9], [5, 3, 1.6]))


@pytest.fixture(scope="module")
def flight() -> dict[str, np.ndarray]:
    """A flight of the parametric model itself, with known parameters."""
    rng = np.random.default_rng(0)
    true = DEFAULT_PARAMS * np.exp(rng.normal(0, 0.2, 16))
    true[10] = -0.02  # net lift: slightly heavy
    x, xs, us, xn = np.array([5, 3, 2, 0.05, 0.02, 0.3, 0, 0, 0, 0, 0, 0.0]), [], [], []
    u = np.zeros(3)
    for k in range(400):
        if k % 4 == 0:
            u = np.clip(rng.normal(0, 0.6, 3), -1, 1)
        nxt = integrate(x[None], u[None], true, (0.44, 0.8), 0.25, 2)[0]
        xs.append(x)
        us.append(u)
        xn.append(nxt)
        x = nxt
    return {"true": true, "x": np.array(xs), "u": np.array(us), "x_next": np.array(xn)}


def test_ode_fit_recovers_its_own_parameters(flight) -> None:
    fit = fit_blimp_ode(flight["x"], flight["u"], flight["x_next"])
    np.testing.assert_allclose(fit.params, flight["true"], rtol=1e-3, atol=1e-6)
    assert np.all(fit.noise_var < 1e-8)


def test_ode_complex_step_jacobian_matches_finite_differences(flight) -> None:
    ode = BlimpODE(flight["true"], np.ones(12))
    x, u = flight["x"][50:53], flight["u"][50:53]
    jac = ode.predict(x, u, jac=True).jac
    h = 1e-6
    fd = np.stack([(ode.change(x + h * e, u) - ode.change(x - h * e, u)) / (2 * h) for e in np.eye(12)], -1)
    np.testing.assert_allclose(jac, fd, atol=1e-6)
    # the mean that comes with the Jacobian (the complex step's real part) is the plain one
    np.testing.assert_allclose(ode.predict(x, u, jac=True).mean, ode.change(x, u), rtol=0, atol=1e-12)


def test_value_and_jacobian_of_a_mean_function_in_one_call() -> None:
    from estimator_service.gp.enhanced import value_and_jacobian

    calls = []

    def f(q):
        calls.append(len(q))
        return np.stack([np.sin(q[:, 0]) * q[:, 1], q[:, 1] ** 2], axis=1)

    x = np.array([[0.3, -1.2], [2.0, 0.5], [-0.7, 3.0]])
    value, jac = value_and_jacobian(f, x)
    assert calls == [3 * (2 * 2 + 1)]  # one batched call
    np.testing.assert_array_equal(value, f(x))
    rows = [[np.cos(x[:, 0]) * x[:, 1], np.sin(x[:, 0])], [0 * x[:, 0], 2 * x[:, 1]]]
    exact = np.stack(rows).transpose(2, 0, 1)  # (M, P, d)
    np.testing.assert_allclose(jac, exact, atol=1e-8)


def test_camera_model_fit_recovers_envelope_axes(flight) -> None:
    truth = CameraModel(CAMS, np.array([0.85, 0.32]), np.ones(10))
    z = truth.mean(flight["x"])
    valid = np.ones((len(z), 2), bool)
    fit = fit_camera_model(CAMS, flight["x"], z, valid)
    np.testing.assert_allclose(fit.semi_axes, [0.85, 0.32], rtol=1e-6)


def test_camera_model_jacobian_linearises_the_model(flight) -> None:
    cam = CameraModel(CAMS, np.array([0.85, 0.32]), np.ones(10))
    x = flight["x"][10:14]
    out = cam.observe(x, jac=True)
    delta = np.random.default_rng(1).normal(size=x.shape) * 1e-4
    moved = cam.mean(x + delta)
    lin = out.mean + np.einsum("mij,mj->mi", out.jac, delta)
    assert np.max(np.abs(moved - lin)) < 1e-5 * max(1.0, np.max(np.abs(out.jac)))
    projected_centre = CAMS[0].project(x[:, :3])
    np.testing.assert_allclose(out.mean[:, :2], projected_centre)
    assert cam.observe(x).jac is None  # a Jacobian only when asked for


@pytest.fixture(scope="module")
def model_dir(flight, tmp_path_factory) -> Path:
    """Every model kind trained on a little data, saved as the factory expects."""
    folder = tmp_path_factory.mktemp("models")
    x, u, xn = flight["x"], flight["u"], flight["x_next"]
    ode = fit_blimp_ode(x, u, xn)
    cam = CameraModel(CAMS, np.array([0.85, 0.32]), np.full(10, 1.0))
    save_parametric(ode, cam, folder / "parametric.npz")
    sel = slice(0, 400, 10)
    xin, dx = np.concatenate([x, u], 1)[sel], (xn - x)[sel]
    z = cam.mean(x)[sel] + 0.5
    quick = {"restarts": 1, "max_iter": 15}
    fits = {
        "gp": lambda a, b: fit_exact(a, b, **quick),
        "sparse": lambda a, b: fit_sparse(a, b, n_pseudo=8, max_iter=15),
        "hetgp": lambda a, b: fit_hetero(a, b, iterations=1, **quick),
    }
    for kind, fit in fits.items():
        save_gp(fit(xin, dx), folder / f"prediction_{kind}.npz")
        save_gp(fit(x[sel], z), folder / f"observation_{kind}.npz")
    pmean = lambda q: ode.change(q[:, :12], q[:, 12:])  # noqa: E731
    save_gp(fit_enhanced(xin, dx, pmean, fit_exact, **quick), folder / "prediction_egp.npz")
    save_gp(fit_enhanced(x[sel], z, cam.mean, fit_exact, **quick), folder / "observation_egp.npz")
    seal(folder, blimp_system(2))
    return folder


def test_parametric_models_round_trip(model_dir: Path, flight) -> None:
    ode, cam = load_parametric(model_dir / "parametric.npz")
    np.testing.assert_allclose(ode.params, flight["true"], rtol=1e-3)
    assert cam.obs_dim == 10


@pytest.mark.parametrize("model_kind", MODEL_KINDS)
@pytest.mark.parametrize("filter_kind", FILTER_KINDS)
def test_every_filter_and_model_pair_builds_and_steps(
    model_dir: Path, flight, filter_kind: str, model_kind: str
) -> None:
    opts = {"n_particles": 200} if filter_kind == "pf" else {}
    filt = build_filter(filter_kind, model_kind, model_dir, **opts)
    belief = GaussianBelief(flight["x"][20], np.eye(12) * 1e-3)
    z = CameraModel(CAMS, np.array([0.85, 0.32]), np.ones(10)).mean(flight["x"][21:22])[0]
    valid = np.array([True] * 5 + [False] * 5)  # one camera reported
    if isinstance(filt, PF):
        rng = np.random.default_rng(0)
        post, info = filt.step(filt.initial(belief, rng), flight["u"][20], z, valid, rng)
        mean = filt.gaussian(post).mean
    else:
        post, info = filt.step(belief, flight["u"][20], z, valid)
        mean = post.mean
    assert info.dof == 5 and np.all(np.isfinite(mean))
    assert abs(mean[5] - flight["x"][21, 5]) < math.pi


def test_unknown_kinds_are_rejected(model_dir: Path) -> None:
    with pytest.raises(ValueError, match="filter kind"):
        build_filter("kf", "gp", model_dir)
    with pytest.raises(ValueError, match="model kind"):
        build_filter("ekf", "nn", model_dir)


@pytest.mark.parametrize("filter_kind", FILTER_KINDS)
def test_filters_print_short(model_dir: Path, filter_kind: str) -> None:
    text = repr(build_filter(filter_kind, "egp", model_dir))
    assert len(text) < 1500 and "e-" not in text.split("noise_var")[0], text  # no factor values


def test_observing_some_columns_equals_the_whole_observation_sliced() -> None:
    """The filters evaluate only the columns some belief read (a landmark type's model only the
    landmarks seen): every model's columns equal its whole observation's, in order, for a
    shared sensor type, a stack placed at interleaved columns, noise scales with floors
    (one row, and one row per query), and a model without the method (sliced)."""
    from estimator_service.models import LinearGaussianObservation
    from estimator_service.models.base import observe_columns
    from estimator_service.models.calibration import NoiseScaledObservation
    from estimator_service.models.gp_models import SharedGPObservation, StackedObservationModel

    rng = np.random.default_rng(3)
    xc = rng.normal(size=(80, 4))  # state (2) and constants (2)
    y = np.stack([np.hypot(*(xc[:, :2] - xc[:, 2:]).T), np.sin(xc[:, 0] - xc[:, 2])], axis=1)
    gp = fit_exact(xc, y + 0.01 * rng.normal(size=y.shape), restarts=0, max_iter=20, rng=rng)
    shared = SharedGPObservation(gp, rng.normal(size=(5, 2)))  # 5 sensors x 2 outputs
    linear = LinearGaussianObservation(rng.normal(size=(3, 2)), np.array([0.1, 0.2, 0.3]))
    placed = (np.array([0, 2, 3, 4, 6, 7, 8, 10, 11, 12]), np.array([1, 5, 9]))  # interleaved
    stacked = StackedObservationModel((shared, linear), placed)
    x = rng.normal(size=(3, 2))
    floor = np.full(13, 0.05)
    in_order = StackedObservationModel((linear, shared))  # no columns: one part after another
    models = [shared, linear, stacked, in_order,
              NoiseScaledObservation(stacked, np.linspace(0.5, 2.0, 13), floor),
              NoiseScaledObservation(stacked, rng.uniform(0.5, 2.0, size=(3, 13)), floor)]  # fmt: skip
    for model in models:
        whole = model.observe(x, jac=True)
        for cols in (np.array([0]), np.array([1, 5]), np.array([2, 3, 8, 12]), np.arange(model.obs_dim)):
            cols = cols[cols < model.obs_dim]
            part = observe_columns(model, x, cols, jac=True)
            np.testing.assert_allclose(part.mean, whole.mean[:, cols], rtol=1e-12, atol=1e-12)
            # a GP variance is its prior minus what the data explain: rounding of the order of
            # eps x the prior (about 1), whatever the variance (1e-14 is ~50 eps; summation orders
            # differ between OpenBLAS's kernels for the CPU: 8.8e-16 on an AMD EPYC)
            np.testing.assert_allclose(
                part.var, np.broadcast_to(whole.var, whole.mean.shape)[:, cols], rtol=1e-12, atol=1e-14
            )
            np.testing.assert_allclose(part.jac, whole.jac[:, cols], rtol=1e-10, atol=1e-12)
            plain = observe_columns(model, x, cols)  # by default no Jacobian, with variances
            assert plain.jac is None and np.array_equal(plain.mean, part.mean)
            np.testing.assert_allclose(plain.var, part.var, rtol=1e-12, atol=1e-14)
        assert model.observe(x).jac is None and np.array_equal(model.observe(x).mean, whole.mean)
    parts = np.concatenate([linear.observe(x).mean, shared.observe(x).mean], axis=1)
    np.testing.assert_array_equal(in_order.observe(x).mean, parts)
    # var=False reaches the GP parts, whose variances are then zeros (the linear part keeps
    # its noise variance), whole or by columns
    np.testing.assert_array_equal(stacked.observe(x, var=False).var[:, placed[0]], 0.0)
    np.testing.assert_array_equal(observe_columns(stacked, x, placed[0][:4], var=False).var, 0.0)
    # placements must cover the observation once: right sizes with a column twice, or the
    # whole set of columns split in the wrong sizes, are refused
    twice = (placed[0], np.array([1, 5, 5]))
    for bad in (twice, (placed[0][:-1], np.array([1, 5, 9, 12]))):
        with pytest.raises(ValueError, match="cover the observation once"):
            StackedObservationModel((shared, linear), bad)


def test_the_calibration_choices_training_reports_are_read_back_per_kind(tmp_path) -> None:
    """``gpbf train``'s summary: per kind with a cross-fitted calibration, whether it was
    applied, its family and factor (and the first-pass candidate a second-pass choice was
    moved from), why, and the held-out log-likelihoods (4 decimals)."""
    import json

    from estimator_service.models.calibration import CALIBRATION_FILE, calibration_choices, read_details

    assert calibration_choices(tmp_path) == {} and read_details(tmp_path) == {}
    chosen = {"applied": True, "family": "matched", "factor": 2.0, "reason": "higher held-out likelihood",
              "from": "one-step x1.4", "chosen": {"mll": 3.123456},
              "uncalibrated": {"mll": 2.98768}}  # fmt: skip
    details = {"noise": {"egp": {"likelihood": chosen}, "gp": {"likelihood": None}, "param": "old form"}}
    (tmp_path / CALIBRATION_FILE).write_text(json.dumps({"details": details}))
    assert read_details(tmp_path) == details
    assert calibration_choices(tmp_path) == {
        "egp": {"applied": True, "family": "matched", "factor": 2.0, "reason": "higher held-out likelihood",
                "from": "one-step x1.4", "heldout_mll": 3.1235, "uncalibrated_mll": 2.9877},
    }  # fmt: skip


def test_camera_jacobian_is_continuous_across_the_ellipse_angles_cut(flight) -> None:
    """An ellipse's orientation (period pi) jumps from about +pi/2 to -pi/2 as the blimp
    yaws; at a state within 1e-9 of the jump the central differences straddle it, and the
    wrapped differences keep the Jacobian equal to its value just beside the cut."""
    cam = CameraModel(CAMS, np.array([0.85, 0.32]), np.ones(10))
    x0 = flight["x"][10].copy()

    def angle(yaw: float) -> float:
        x = x0.copy()
        x[5] = yaw
        return float(cam.mean(x[None])[0, 4])

    yaws = np.linspace(-math.pi, math.pi, 721)
    jumps = [i for i in range(720) if abs(angle(yaws[i + 1]) - angle(yaws[i])) > 2.0]
    assert jumps, "no yaw puts camera 0's ellipse angle across its cut"
    lo, hi = yaws[jumps[0]], yaws[jumps[0] + 1]
    while hi - lo > 1e-9:  # bisect onto the cut
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if abs(angle(mid) - angle(lo)) < 1.0 else (lo, mid)
    at, beside = x0.copy(), x0.copy()
    at[5], beside[5] = 0.5 * (lo + hi), 0.5 * (lo + hi) + 1e-4
    j = cam.observe(np.stack([at, beside]), jac=True).jac[:, 4]
    assert np.all(np.abs(j) < 1e3)
    np.testing.assert_allclose(j[0], j[1], rtol=0.05, atol=1e-3 * np.abs(j[1]).max())


def test_the_parametric_prediction_gives_no_jacobian_unless_asked(flight) -> None:
    ode = BlimpODE(DEFAULT_PARAMS, np.full(12, 1e-4))
    x, u = flight["x"][:3], flight["u"][:3]
    plain, full = ode.predict(x, u), ode.predict(x, u, jac=True)
    assert plain.jac is None and full.jac.shape == (3, 12, 12)
    np.testing.assert_allclose(plain.mean, full.mean, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(plain.var, np.full((3, 12), 1e-4))


def test_an_ellipse_is_read_from_its_shape_matrix() -> None:
    """``S = R(t) diag((w/2)^2, (h/2)^2) R(t)^T`` is the ellipse of width ``w``, height ``h``
    and orientation ``t``, for batches of any leading shape; an upright ellipse (``t = pi/2``)
    reads ``-pi/2`` by the one angle rule."""
    from estimator_service.models.camera import ellipse_from_shape

    rng = np.random.default_rng(6)
    w, h = rng.uniform(20, 60, (3, 4)), rng.uniform(0.4, 1.6, (3, 4))  # (h/2)^2 < 1
    t = rng.uniform(-1.5, 1.5, (3, 4))
    t[0, 0] = math.pi / 2
    c, s = np.cos(t), np.sin(t)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # (3, 4, 2, 2)
    shape = rot @ (np.stack([w / 2, h / 2], -1)[..., None] ** 2 * np.eye(2)) @ rot.swapaxes(-1, -2)
    centre = rng.uniform(0, 600, (3, 4, 2))
    got = ellipse_from_shape(centre, shape)
    want = np.stack([centre[..., 0], centre[..., 1], w, h, np.where(t == math.pi / 2, -math.pi / 2, t)], -1)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)


def test_camera_fit_checks_each_shape_and_measures_the_noise_of_the_frames_seen(flight) -> None:
    """Each mismatch alone is refused; the noise is the mean squared residual of the frames
    seen (angles wrapped), per output, plus 1e-9, none of the unseen frames counted."""
    from estimator_service.angles import wrap_angle
    from estimator_service.models.camera import project_ellipses

    x = flight["x"][:120]
    rng = np.random.default_rng(7)
    z = CameraModel(CAMS, np.array([0.85, 0.32]), np.ones(10)).mean(x) + rng.normal(0, 1.5, (120, 10))
    valid = rng.uniform(size=(120, 2)) < 0.8
    valid[:, 1] = np.arange(120) == 5  # the second camera saw one frame
    for bad in ((x[:-1], z, valid), (x, z[:, :-1], valid), (x, z, valid[:, :1])):
        with pytest.raises(ValueError, match="need x"):
            fit_camera_model(CAMS, *bad)
    fit = fit_camera_model(CAMS, x, z, valid)
    periods = fit.obs_periods
    r = wrap_angle(project_ellipses(CAMS, x, fit.semi_axes) - z, periods)
    seen = np.repeat(valid, 5, axis=1)
    want = np.where(seen, r * r, 0.0).sum(axis=0) / seen.sum(axis=0) + 1e-9
    np.testing.assert_allclose(fit.noise_var, want, rtol=1e-12)
    np.testing.assert_allclose(fit.noise_var[5:], r[5, 5:] ** 2 + 1e-9, rtol=1e-12)
    assert fit.noise_var.shape == (10,)


def test_the_camera_rotation_and_ellipses_agree_with_the_simulators_own_geometry() -> None:
    """Against the simulator's independent code (``gpbf_env.camera``, undistorted): the
    body-to-world rotation equals ``Rz(psi) Ry(theta) Rx(phi)`` exactly, and the projected
    principal axes give the closed-form rim ellipse's centre, size and orientation to a few
    per cent (the model is that approximation; a wrong axis or scale is off many fold)."""
    import dataclasses

    from estimator_service.models.rotation import euler_matrix
    from gpbf_env.camera import default_cameras, euler_to_matrix, outline_ellipses

    rng = np.random.default_rng(8)
    euler = np.c_[rng.uniform(-0.5, 0.5, (20, 2)), rng.uniform(-math.pi, math.pi, 20)]
    np.testing.assert_allclose(euler_matrix(euler), euler_to_matrix(euler), atol=1e-15)
    sim = tuple(dataclasses.replace(c, k1=0.0, k2=0.0) for c in default_cameras((10.0, 6.0, 4.0)))
    cams = tuple(PinholeCalibration(c.position, c.rotation, c.focal, c.principal_point) for c in sim)
    x = np.zeros((20, 12))
    x[:, :3] = rng.uniform([3, 2, 1.2], [7, 4, 2.4], (20, 3))
    x[:, 3:6] = euler
    ours = CameraModel(cams, np.array([0.85, 0.32]), np.ones(5 * len(cams))).mean(x).reshape(20, -1, 5)
    truth, seen = outline_ellipses(sim, x[:, :3], euler_to_matrix(euler), (0.85, 0.32, 0.32))
    truth = truth.reshape(20, -1, 5)
    ok = seen.reshape(20, -1)
    assert ok.mean() > 0.5
    np.testing.assert_allclose(ours[ok][:, :2], truth[ok][:, :2], atol=10.0)  # centre, px
    np.testing.assert_allclose(ours[ok][:, 2:4], truth[ok][:, 2:4], rtol=0.05)  # width, height (1.3 %)
    turn = (ours[ok][:, 4] - truth[ok][:, 4] + math.pi / 2) % math.pi - math.pi / 2
    round_ = truth[ok][:, 3] > 0.9 * truth[ok][:, 2]  # a near-circle's orientation is arbitrary
    assert np.all(np.abs(turn[~round_]) < 0.02)  # 0.003 rad measured


def test_the_odes_kinematics_are_rigid_body_rates() -> None:
    """Whatever the forces, position changes at ``R(euler) v`` (body velocities turned into the
    world by the simulator's own ``Rz Ry Rx``) and the Euler angles at the ZYX rates
    ``phi' = p + (q sin phi + r cos phi) tan theta``, ``theta' = q cos phi - r sin phi``,
    ``psi' = (q sin phi + r cos phi) / cos theta``; read from one RK4 step of 1e-7 s."""
    from gpbf_env.camera import euler_to_matrix

    rng = np.random.default_rng(9)
    x = np.c_[rng.uniform(-1, 1, (6, 3)), rng.uniform(-0.6, 0.6, (6, 2)), rng.uniform(-3, 3, 6),
              rng.uniform(-0.5, 0.5, (6, 6))]  # fmt: skip
    u = rng.uniform(-1, 1, (6, 3))
    dt = 1e-7
    rate = (integrate(x, u, DEFAULT_PARAMS, (0.44, 0.8), dt, 1) - x) / dt
    v, (phi, theta), (p, q, r) = x[:, 6:9], x[:, 3:5].T, x[:, 9:12].T
    np.testing.assert_allclose(rate[:, :3], np.einsum("mij,mj->mi", euler_to_matrix(x[:, 3:6]), v), atol=1e-6)
    turn = q * np.sin(phi) + r * np.cos(phi)
    euler_rates = np.c_[p + turn * np.tan(theta), q * np.cos(phi) - r * np.sin(phi), turn / np.cos(theta)]
    np.testing.assert_allclose(rate[:, 3:6], euler_rates, atol=1e-6)


def test_the_ode_fit_checks_its_shapes_and_keeps_the_measured_constants(flight) -> None:
    """Shapes and non-finite values refused by name; the measured constants kept."""
    x, u, xn = flight["x"][:60], flight["u"][:60], flight["x_next"][:60]
    for bad in ((x[:, :11], u, xn[:, :11]), (x, u[:, :2], xn), (x, u, xn[:-1])):
        with pytest.raises(ValueError, match=r"need x \(N, 12\)"):
            fit_blimp_ode(*bad)
    for which in range(3):  # a NaN or an infinity in any of the three arrays
        arrays = [x.copy(), u.copy(), xn.copy()]
        arrays[which][7, 1] = np.nan if which != 1 else np.inf
        with pytest.raises(ValueError, match="NaN or Inf"):
            fit_blimp_ode(*arrays)
    ode = fit_blimp_ode(x, u, xn, mass=0.5, tail_arm=0.7, dt=0.25, max_nfev=5)
    assert (ode.mass, ode.tail_arm, ode.dt) == (0.5, 0.7, 0.25)


def test_gp_model_wrappers_pass_the_gps_variances_through_by_default() -> None:
    """The prediction and observation wrappers (and a noise-scaled prediction) return the
    GP's own variances unless told not to, and the state block of its Jacobian."""
    from estimator_service.gp import ExactGP, Scaler
    from estimator_service.models.calibration import NoiseScaledPrediction
    from estimator_service.models.gp_models import GPObservationModel, GPPredictionModel

    rng = np.random.default_rng(10)
    xs, ys = rng.uniform(-1, 1, (25, 3)), rng.normal(size=(25, 2))
    theta = np.log([[0.8, 1.1, 0.9, 1.0, 0.2], [1.3, 0.7, 1.2, 2.0, 0.1]])
    gp = ExactGP.from_theta(xs, ys, theta, Scaler(np.zeros(3), np.ones(3)), Scaler(np.zeros(2), np.ones(2)))
    x, u = rng.uniform(-1, 1, (4, 2)), rng.uniform(-1, 1, (4, 1))
    want = gp.predict(np.c_[x, u], return_jac=True)
    pred = GPPredictionModel(gp, 2)
    np.testing.assert_allclose(pred.predict(x, u).var, want.var, rtol=1e-12)
    np.testing.assert_allclose(pred.predict(x, u, jac=True).jac, want.jac[:, :, :2], rtol=1e-12)
    scaled = NoiseScaledPrediction(pred, np.array([2.0, 3.0]))
    np.testing.assert_allclose(scaled.predict(x, u).var, want.var * [2.0, 3.0], rtol=1e-12)
    with pytest.raises(ValueError):
        NoiseScaledPrediction(pred, np.ones((1, 1, 2)))  # one scale per output, or per row and output
    obs = GPObservationModel(gp)
    np.testing.assert_allclose(obs.observe(np.c_[x, u]).var, want.var, rtol=1e-12)
    # var=False: the variance skipped and returned as zeros of the mean's shape (the contract)
    for out in (obs.observe(np.c_[x, u], var=False), pred.predict(x, u, var=False)):
        assert out.var.shape == (4, 2) and out.var.dtype == np.float64 and not out.var.any()
    assert obs.observe(np.c_[x, u]).jac is None and pred.predict(x, u).jac is None  # only when asked


def test_the_odes_dynamics_are_newton_euler() -> None:
    """With drag, lift, righting moment and controls switched off, momentum obeys
    ``M v' = -w x (M v)`` and ``J w' = -w x (J w)`` (``numpy.cross``), for distinct masses;
    thrust alone accelerates along ``(cos mu, 0, sin mu)`` and pitches by the fan's arm."""
    rng = np.random.default_rng(11)
    th = np.zeros(16)
    th[[0, 1, 2, 3]] = [0.6, 0.9, 0.02, 0.1]  # m2, m3, j1, j_lat
    fixed, dt = (0.44, 0.8), 1e-7
    x = np.c_[np.zeros((5, 3)), rng.uniform(-0.4, 0.4, (5, 3)), rng.uniform(-0.5, 0.5, (5, 6))]
    rate = (integrate(x, np.zeros((5, 3)), th, fixed, dt, 1) - x) / dt
    m, j = np.array([0.44, 0.6, 0.9]), np.array([0.02, 0.1, 0.1])
    v, w = x[:, 6:9], x[:, 9:12]
    np.testing.assert_allclose(m * rate[:, 6:9], -np.cross(w, m * v), atol=1e-6)
    np.testing.assert_allclose(j * rate[:, 9:12], -np.cross(w, j * w), atol=1e-6)
    th[[12, 13, 15]] = [0.15, 1.5, 0.4]  # k_thrust, k_angle, fan_arm
    u = np.array([[0.8, 0.3, 0.0]])
    rest = np.zeros((1, 12))
    rate = (integrate(rest, u, th, fixed, dt, 1) - rest) / dt
    thrust, mu = 0.15 * 0.8, 1.5 * 0.3
    np.testing.assert_allclose(
        rate[0, 6:9], [thrust * np.cos(mu) / 0.44, 0.0, thrust * np.sin(mu) / 0.9], atol=1e-6
    )
    np.testing.assert_allclose(rate[0, 9:12], [0.0, -0.4 * thrust * np.cos(mu) / 0.1, 0.0], atol=1e-6)


def test_the_odes_forces_and_moments_are_the_documented_ones() -> None:
    """Every force and moment of the module's description, computed here independently
    (the world vertical in body axes from the simulator's rotation, moments by
    ``numpy.cross``): linear drag, net lift along world z, fan thrust along
    ``(cos mu, 0, sin mu)`` at the fan's arm, the tail's side force at the tail's arm, the
    righting moment ``righting (e_z x g)`` and rotational drag, in ``M v' = F - w x Mv`` and
    ``J w' = T - w x Jw`` (one RK4 step of 1e-7 s)."""
    from gpbf_env.camera import euler_to_matrix

    rng = np.random.default_rng(12)
    th = DEFAULT_PARAMS.copy()
    th[10] = -0.03  # net lift: slightly heavy
    m1, l_t = 0.44, 0.8
    x = np.c_[
        np.zeros((6, 3)),
        rng.uniform(-0.5, 0.5, (6, 2)),
        rng.uniform(-3, 3, 6),
        rng.uniform(-0.5, 0.5, (6, 6)),
    ]
    u = rng.uniform(-1, 1, (6, 3))
    rate = (integrate(x, u, th, (m1, l_t), 1e-7, 1) - x) / 1e-7
    m2, m3, j1, j_lat, d1, d2, d3, e1, e2, e3, lift, right, k_t, k_mu, k_tl, l_f = th
    m, j = np.array([m1, m2, m3]), np.array([j1, j_lat, j_lat])
    v, w = x[:, 6:9], x[:, 9:12]
    g = euler_to_matrix(x[:, 3:6])[:, 2, :]  # world z in body axes
    thrust, mu, tail = k_t * u[:, 0], k_mu * u[:, 1], k_tl * u[:, 2]
    fan = np.c_[thrust * np.cos(mu), np.zeros(6), thrust * np.sin(mu)]
    force = fan + np.c_[np.zeros(6), tail, np.zeros(6)] - [d1, d2, d3] * v + lift * g
    moment = (
        right * np.cross([0.0, 0.0, 1.0], g)
        + np.cross([0.0, 0.0, -l_f], fan)  # the fan at fan_arm below the centre (body z up)
        + np.cross([-l_t, 0.0, 0.0], np.c_[np.zeros(6), tail, np.zeros(6)])  # the tail behind it
        - [e1, e2, e3] * w
    )
    np.testing.assert_allclose(m * rate[:, 6:9], force - np.cross(w, m * v), atol=1e-6)
    np.testing.assert_allclose(j * rate[:, 9:12], moment - np.cross(w, j * w), atol=1e-6)


def test_the_ode_integration_is_fourth_order_against_a_tight_solver() -> None:
    """``integrate`` (classical Runge-Kutta, ``n_sub`` steps of ``dt / n_sub``) against SciPy's
    DOP853 at 1e-12 over one 0.25 s step from states with fast rotation: within 5e-4 at the
    default two substeps, and the error shrinks about 16-fold per halving of the substep
    (fourth order; a wrong stage coefficient leaves first or second order)."""
    from scipy.integrate import solve_ivp

    from estimator_service.models.blimp import _derivative

    rng = np.random.default_rng(4)
    x = np.c_[rng.uniform(-1, 1, (6, 3)), rng.uniform(-0.6, 0.6, (6, 2)), rng.uniform(-3, 3, 6),
              rng.uniform(-0.5, 0.5, (6, 6))]  # fmt: skip
    u, fixed = rng.uniform(-1, 1, (6, 3)), (0.44, 0.8)

    def rate(k: int):
        return lambda t, y: _derivative(y[:, None], u[k][:, None], DEFAULT_PARAMS, fixed)[:, 0]

    ref = np.array([solve_ivp(rate(k), (0.0, 0.25), x[k], method="DOP853", rtol=1e-12, atol=1e-12).y[:, -1]
                    for k in range(len(x))])  # fmt: skip
    err = [np.abs(integrate(x, u, DEFAULT_PARAMS, fixed, 0.25, n) - ref).max() for n in (2, 4, 8)]
    assert err[0] < 5e-4
    assert 12.0 < err[0] / err[1] < 24.0 and 12.0 < err[1] / err[2] < 24.0, err


def test_ode_fit_starts_at_the_given_parameters(flight) -> None:
    """A fit started at the parameters that made the data stops there: its start is the
    given point, parameters below 1 included (fitted in log space)."""
    assert np.any(flight["true"] < 1.0)
    fit = fit_blimp_ode(flight["x"][:100], flight["u"][:100], flight["x_next"][:100],
                        initial=flight["true"], max_nfev=1)  # fmt: skip
    np.testing.assert_allclose(fit.params, flight["true"], rtol=1e-12, atol=1e-15)


def test_ode_fit_minimises_each_states_error_over_its_spread(flight) -> None:
    """On noisy transitions (the weighting then matters) the fit is a stationary point of
    the documented objective, the one-step errors each divided by its state's standard
    deviation of change: central differences of that sum of squares in the fitted
    coordinates (log of the positive parameters) vanish at the fit (1e-4 here; weighting by
    the spread instead of dividing leaves 33)."""
    from estimator_service.angles import wrap_angle
    from estimator_service.models.blimp import _SIGNED, PARAM_NAMES

    rng = np.random.default_rng(0)
    x, u = flight["x"][:200], flight["u"][:200]
    change = flight["x_next"][:200] - x
    noisy = flight["x_next"][:200] + rng.normal(size=x.shape) * 0.3 * change.std(axis=0)
    fit = fit_blimp_ode(x, u, noisy)
    target = noisy - x
    target[:, 3:6] = wrap_angle(target[:, 3:6])
    scale, signed = target.std(axis=0), np.array([n in _SIGNED for n in PARAM_NAMES])

    def objective(z: np.ndarray) -> float:
        params = np.where(signed, z, np.exp(z))
        err = (BlimpODE(params, np.ones(12), 0.44, 0.8, 0.25).change(x, u) - target) / scale
        return float(np.sum(err * err))

    def gradient(params: np.ndarray) -> np.ndarray:
        z, h = np.where(signed, params, np.log(np.abs(np.where(signed, 1.0, params)))), 1e-5
        steps = np.eye(len(PARAM_NAMES))
        return np.array([(objective(z + h * e) - objective(z - h * e)) / (2 * h) for e in steps])

    assert np.abs(gradient(fit.params)).max() < 1e-6 * np.abs(gradient(DEFAULT_PARAMS)).max()


def test_ode_fit_at_another_step_from_a_given_start(flight) -> None:
    """One-step data at dt = 0.5 s are fitted by a model stepping 0.5 s (not the default
    0.25 s), starting from the guess given; its noise variance is each state's mean squared
    one-step residual of that model."""
    x, u = flight["x"][:150], flight["u"][:150]
    xn = integrate(x, u, flight["true"], (0.44, 0.8), 0.5, 2)
    fit = fit_blimp_ode(x, u, xn, dt=0.5, initial=flight["true"] * 1.05)
    assert fit.dt == 0.5
    np.testing.assert_allclose(fit.params, flight["true"], rtol=1e-3, atol=1e-6)
    from estimator_service.angles import wrap_angle

    change = xn - x
    change[:, 3:6] = wrap_angle(change[:, 3:6])
    residual = fit.change(x, u) - change  # each state's own mean square, floored above zero
    np.testing.assert_allclose(fit.noise_var, np.mean(residual**2, axis=0) + 1e-12, rtol=1e-6)
    assert fit.noise_var.shape == (12,) and np.all(fit.noise_var > 0)
