"""Camera geometry: projection, closed-form conics, rendered-and-fitted ellipses."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from gpbf_env.camera import (
    Camera,
    default_cameras,
    ellipse_from_points,
    euler_to_matrix,
    outline_ellipses,
)
from gpbf_env.imaging import fit_ellipse_image, render_frame

ROOM = (10.0, 6.0, 4.0)
AXES = (0.85, 0.32, 0.32)


def test_point_on_optical_axis_projects_to_principal_point() -> None:
    for cam in default_cameras(ROOM):
        pix, depth = cam.project(cam.position + 3.7 * cam.rotation[2])
        np.testing.assert_allclose(pix, cam.principal_point, atol=1e-9)
        assert depth == pytest.approx(3.7)
        _, behind = cam.project(cam.position - 1.0 * cam.rotation[2])
        assert behind < 0


@pytest.mark.slow
def test_sphere_on_axis_gives_circle_of_tangent_cone_size() -> None:
    cam = dataclasses.replace(default_cameras(ROOM)[0], k1=0.0, k2=0.0)
    rho, d = 0.4, 5.0
    centre = cam.position + d * cam.rotation[2]
    ell, vis = outline_ellipses((cam,), centre[None], np.eye(3)[None], (rho, rho, rho))
    expected = 2 * cam.focal * rho / math.sqrt(d * d - rho * rho)
    assert vis[0, 0]
    np.testing.assert_allclose(ell[0, 0, :2], cam.principal_point, atol=1e-9)
    np.testing.assert_allclose(ell[0, 0, 2:4], [expected, expected], rtol=1e-9)


def test_closed_form_conic_matches_projected_ellipsoid_rim() -> None:
    """Without distortion the outline conic equals the projected occluding contour."""
    cam = dataclasses.replace(default_cameras(ROOM)[0], k1=0.0, k2=0.0)
    pos, rot = np.array([4.0, 2.5, 1.5]), euler_to_matrix(np.array([[0.2, -0.1, 0.9]]))[0]
    ell, _ = outline_ellipses((cam,), pos[None], rot[None], AXES)
    # Dense sample of the ellipsoid surface: the hull of its projection is the outline.
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 400), np.linspace(0, np.pi, 200))
    surf = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)], -1).reshape(-1, 3)
    pts = pos + (surf * AXES) @ rot.T
    pix, _ = cam.project(pts, distort=False)
    cx, cy, w, h, a = ell[0, 0]
    d = pix - [cx, cy]
    x = d[:, 0] * math.cos(a) + d[:, 1] * math.sin(a)
    y = -d[:, 0] * math.sin(a) + d[:, 1] * math.cos(a)
    rad = (x / (w / 2)) ** 2 + (y / (h / 2)) ** 2
    assert rad.max() == pytest.approx(1.0, abs=2e-3)  # touches the conic, never outside


@pytest.mark.parametrize("seed", range(4))
def test_closed_form_and_rendered_fit_agree_on_clean_frames(seed: int) -> None:
    rng = np.random.default_rng(seed)
    cams = default_cameras(ROOM)
    pos = rng.uniform([2.5, 1.5, 1.0], [7.5, 4.5, 3.0])
    rot = euler_to_matrix(np.array([[rng.normal(0, 0.1), rng.normal(0, 0.1), rng.uniform(-3, 3)]]))
    closed, vis = outline_ellipses(cams, pos[None], rot, AXES)
    for k, cam in enumerate(cams):
        fitted = fit_ellipse_image(cam, render_frame(cam, pos, rot[0], AXES, rng=None))
        assert vis[0, k] and fitted is not None
        np.testing.assert_allclose(fitted[:4], closed[0, k, :4], atol=3.0)  # pixels
        if closed[0, k, 2] > 1.2 * closed[0, k, 3]:  # orientation defined
            da = (fitted[4] - closed[0, k, 4] + np.pi / 2) % np.pi - np.pi / 2
            assert abs(da) < 0.05


def test_noisy_rendered_frame_still_fits() -> None:
    cam = default_cameras(ROOM)[0]
    pos, rot = np.array([5.0, 3.0, 1.5]), np.eye(3)
    clean = fit_ellipse_image(cam, render_frame(cam, pos, rot, AXES))
    noisy = fit_ellipse_image(cam, render_frame(cam, pos, rot, AXES, np.random.default_rng(0)))
    np.testing.assert_allclose(noisy, clean, atol=0.5)


def test_behind_or_outside_view_is_invalid() -> None:
    cam = default_cameras(ROOM)[0]
    behind = cam.position - 2.0 * cam.rotation[2]
    aside = cam.position + 2.0 * cam.rotation[2] + 5.0 * cam.rotation[0]
    _, vis = outline_ellipses((cam,), np.stack([behind, aside]), np.stack([np.eye(3)] * 2), AXES)
    assert not vis.any()


def test_ellipse_angle_has_period_pi_and_moment_fit_is_exact() -> None:
    t = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    for ang in (0.3, 0.3 + np.pi, -1.2, np.pi / 2):
        c, s = np.cos(ang), np.sin(ang)
        x = 100 + 40 * np.cos(t) * c - 10 * np.sin(t) * s
        y = 80 + 40 * np.cos(t) * s + 10 * np.sin(t) * c
        pts = np.stack([x, y], -1)
        cx, cy, w, h, a = ellipse_from_points(pts)
        np.testing.assert_allclose([cx, cy, w, h], [100, 80, 80, 20], atol=1e-9)
        assert -np.pi / 2 < a <= np.pi / 2
        assert abs((a - ang + np.pi / 2) % np.pi - np.pi / 2) < 1e-9


def test_camera_look_at_is_a_rotation() -> None:
    cam = Camera.look_at(np.array([0.0, 0.0, 3.0]), np.array([5.0, 3.0, 1.0]))
    np.testing.assert_allclose(cam.rotation @ cam.rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(cam.rotation) == pytest.approx(1.0)


def test_knocked_camera_sees_its_old_axis_off_centre_by_the_pan() -> None:
    from gpbf_env.core import WorldConfig

    plain, hit = WorldConfig().cameras, WorldConfig(camera_knock_deg=3.0).cameras
    old_axis = plain[0].position + 4.0 * plain[0].rotation[2]
    pix, _ = hit[0].project(old_axis, distort=False)
    old, new = plain[0].rotation[2], hit[0].rotation[2]  # optical axes
    turn = math.atan2(new[1], new[0]) - math.atan2(old[1], old[0])
    assert math.degrees(turn) == pytest.approx(3.0) and new[2] == pytest.approx(old[2])  # a pan: tilt kept
    offset = np.hypot(*(pix - np.array(hit[0].principal_point)))
    assert offset == pytest.approx(hit[0].focal * math.tan(math.acos(old @ new)), rel=1e-9)
    assert offset > 15.0  # pixels: a visible shift for a tracker trained on the old pose
    np.testing.assert_allclose(hit[0].position, plain[0].position)
    np.testing.assert_allclose(hit[1].rotation, plain[1].rotation)  # the others keep their pose
    with pytest.raises(ValueError, match="camera_knock_deg"):
        WorldConfig(camera_knock_deg=float("nan"))
