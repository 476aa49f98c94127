"""Past poses of the blimps, and the motion-capture system that measures them.

The paper's ground truth came from a 120 Hz motion-capture system; velocities were the
slope of a smoothed window of its poses (Ko & Fox 2009, Sect. 6.1.1). :class:`PoseTrack`
keeps each blimp's pose and pose rate at the RK4 knots of its last few env steps and
interpolates between them (cubic Hermite, exact at the knots); :func:`measure` samples it
at 120 Hz, adds marker noise and fits the slope, and camera latency reads the pose at
the exposure time from the same track.

Random draws: :data:`AUX_DRAWS` standard normals per blimp and step from a generator
spawned from the env's own at reset, so the world's trajectory and camera noise do not
depend on these draws.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from gpbf_env.dynamics import wrap_angle
from gpbf_env.mocap_kernel import measure_kernel, pose_rates

__all__ = ["AUX_DRAWS", "MOCAP_RATE_HZ", "PoseTrack", "measure"]

FloatArray = NDArray[np.float64]

MOCAP_RATE_HZ = 120.0  # the paper's motion-capture rate
MOCAP_SAMPLES = 12  # poses in the slope window: 11 / 120 s, about 100 ms
POSITION_STD_M = 0.5e-3  # sub-millimetre marker noise
ANGLE_STD_RAD = math.radians(0.05)
AUX_DRAWS = MOCAP_SAMPLES * 6 + 1  # marker noise, then the camera-latency jitter
_LAGS = np.arange(MOCAP_SAMPLES) / MOCAP_RATE_HZ
_SLOPE = -(_LAGS - _LAGS.mean()) / np.sum((_LAGS - _LAGS.mean()) ** 2)  # least-squares slope
_STD = np.array([POSITION_STD_M] * 3 + [ANGLE_STD_RAD] * 3)


def wrap(a: FloatArray) -> FloatArray:
    """Angles wrapped to ``[-pi, pi)`` (the dynamics' own rule)."""
    return wrap_angle(a)


class PoseTrack:
    """Poses and pose rates of ``N`` blimps at the RK4 knots of their last ``depth`` steps.

    Parameters
    ----------
    n
        Number of blimps.
    n_sub
        RK4 sub-steps per env step.
    dt
        Env step (s).
    depth
        Env steps kept; lags up to ``depth * dt`` can be read.
    """

    def __init__(self, n: int, n_sub: int, dt: float, depth: int) -> None:
        self.n_sub, self.dt, self.depth = n_sub, dt, depth
        # [step back, knot, pose|rate, blimp]; angles continuous along the whole track
        self._buf = np.zeros((depth, n_sub + 1, 12, n))
        at, weights = self._slope_weights()
        self._slope_at, self._slope_w = at, weights

    def reset_rows(self, rows: NDArray[np.int64], states: FloatArray) -> None:
        """Blimps ``rows`` held still at the poses of ``states`` (len(rows), 12) until now."""
        self._buf[:, :, :6, rows] = states[:, :6].T
        self._buf[:, :, 6:, rows] = 0.0

    def push(self, knots: FloatArray) -> None:
        """Append one env step: ``knots`` (n_sub + 1, 12, N) states from ``rk4_step``."""
        self._buf[1:] = self._buf[:-1].copy()
        last = self._buf[1, -1, 3:6].copy()
        self._buf[0, :, :6] = knots[:, :6]
        self._buf[0, :, 3:6] += last - knots[0, 3:6]  # undo the wrap at the step boundary
        pose_rates(knots, self._buf[0, :, 6:])

    def _slope_weights(self) -> tuple[NDArray[np.int64], FloatArray]:
        """The slope of :func:`measure`'s samples as weights (L, 2) on the poses and rates
        of the knots (L, 2) (step back, knot) in the window."""
        j, i, u = self._locate(np.clip(_LAGS, 0.0, self.depth * self.dt))
        h = self.dt / self.n_sub
        sp = np.zeros((self.depth, self.n_sub + 1))
        sr = np.zeros_like(sp)
        for m in range(MOCAP_SAMPLES):  # once per track: the Hermite basis at each sample
            a, b = (j[m], i[m]), (j[m], i[m] + 1)
            um = u[m]
            sp[a] += _SLOPE[m] * (2 * um**3 - 3 * um**2 + 1)
            sr[a] += _SLOPE[m] * (um**3 - 2 * um**2 + um) * h
            sp[b] += _SLOPE[m] * (-2 * um**3 + 3 * um**2)
            sr[b] += _SLOPE[m] * (um**3 - um**2) * h
        at = np.argwhere((sp != 0) | (sr != 0))  # the few knots in the window, in a fixed order
        return at, np.stack([sp[tuple(at.T)], sr[tuple(at.T)]], axis=1)

    def _locate(self, lag: FloatArray) -> tuple[NDArray[np.int64], NDArray[np.int64], FloatArray]:
        """Step back ``j``, knot ``i`` and fraction ``u`` of the segment holding each lag."""
        n_sub, dt = self.n_sub, self.dt
        j = np.minimum(np.floor(lag / dt), self.depth - 1).astype(np.int64)
        x = np.clip((dt - (lag - j * dt)) * (n_sub / dt), 0.0, n_sub)
        i = np.minimum(np.floor(x), n_sub - 1).astype(np.int64)
        return j, i, x - i

    def at(self, lag: FloatArray) -> FloatArray:
        """Poses ``(M, N, 6)`` at ``lag`` (M, N) seconds before now (angles wrapped)."""
        j, i, u = self._locate(np.clip(lag, 0.0, self.depth * self.dt))
        u = u[..., None]
        cols = np.broadcast_to(np.arange(self._buf.shape[3]), lag.shape)
        a, b = self._buf[j, i, :, cols], self._buf[j, i + 1, :, cols]  # (M, N, 12)
        h = self.dt / self.n_sub
        u2, u3 = u * u, u * u * u
        pose = (
            (2 * u3 - 3 * u2 + 1) * a[..., :6]
            + (u3 - 2 * u2 + u) * h * a[..., 6:]
            + (-2 * u3 + 3 * u2) * b[..., :6]
            + (u3 - u2) * h * b[..., 6:]
        )
        pose[..., 3:] = wrap(pose[..., 3:])
        return pose


def measure(track: PoseTrack, noise: FloatArray) -> FloatArray:
    """The motion-capture state ``(N, 12)`` of every blimp now.

    Pose: the newest of 12 samples at 120 Hz with marker noise. Velocities: the
    least-squares slope of the noisy samples over the window (about 100 ms, so they lag
    the truth by about 46 ms), turned into body-frame velocity and body rates with the
    measured attitude.

    Parameters
    ----------
    track
        The blimps' recent poses.
    noise: (N, AUX_DRAWS)
        Standard normal draws; the first ``12 * 6`` are used.
    """
    n = track._buf.shape[3]
    noise = np.ascontiguousarray(noise, dtype=np.float64)
    if noise.ndim != 2 or noise.shape[0] != n or noise.shape[1] < MOCAP_SAMPLES * 6:
        raise ValueError(f"noise must have shape ({n}, >= {MOCAP_SAMPLES * 6}), got {noise.shape}")
    out = np.empty((n, 12))
    measure_kernel(track._buf, track._slope_at, track._slope_w, noise, _STD, _SLOPE, out)
    return out
