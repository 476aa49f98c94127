"""Pieces shared by the single and the batched blimp environments."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from gpbf_env.camera import (
    N_BOUNDARY,
    Camera,
    default_cameras,
    euler_to_matrix,
    outline_ellipses,
)
from gpbf_env.imaging import fit_ellipse_image, render_frame
from gpbf_env.mocap import MOCAP_RATE_HZ, MOCAP_SAMPLES
from gpbf_env.params import BlimpParams, randomize_params
from gpbf_env.reality import check_preset, check_strength, lab_effects
from gpbf_env.tasks import TASKS, RewardWeights

__all__ = ["STATE_NAMES", "WorldConfig", "camera_lag", "check_action", "initial_state", "observe"]

FloatArray = NDArray[np.float64]
MAX_KNOCK_DEG = 30.0  # the largest camera knock a world accepts (degrees)
STATE_NAMES = ("x", "y", "z", "roll", "pitch", "yaw", "u", "v", "w", "p", "q", "r")


@dataclass(frozen=True)
class WorldConfig:
    """Everything that defines an episode's world apart from the random draws.

    Attributes
    ----------
    task
        ``"hover"`` or ``"waypoint"``.
    room
        Lab room size ``(length, width, height)`` in m; the origin is a floor corner.
    dt
        Env step (s), 0.25 s is the paper's 4 Hz.
    substeps
        Fixed RK4 sub-steps per env step.
    camera_rate_hz
        Frame rate of every camera; frames are staggered between cameras.
    n_cameras
        Number of wall cameras (1-4).
    camera_knock_deg
        Pan of the first camera about the vertical (degrees) away from the pose the others
        are calibrated in, as if it had been knocked; ``cameras`` describes the knocked pose
        (0: none). A filter calibrated before the knock still uses the old pose.
    pixel_noise
        Standard deviation (px) of the noise on each outline sample (closed-form mode).
    camera_mode
        ``"closed_form"`` (fast: exact outline conic, distortion, noise, moment fit) or
        ``"rendered"`` (slow, like the paper's cameras: a noisy 640x480 image, background
        subtraction, ellipse fit to the foreground).
    image_noise
        Grey-level noise standard deviation of rendered images.
    params
        Nominal physical parameters.
    randomize
        Domain randomisation scale (0 disables), see :func:`randomize_params`.
    reality
        ``"lab"`` (default: the unmodelled effects U1-U8 and C1 of :class:`BlimpParams`,
        indoor drafts), ``"clean"`` (the textbook world the paper's parametric model
        describes) or ``"drafty"`` (lab with the nominal, stronger gusts); see
        :mod:`gpbf_env.reality`.
    reality_strength
        Scale on every unmodelled effect (0 reproduces ``clean`` bit for bit, 1 the lab
        magnitudes); None takes the preset's.
    """

    task: str = "hover"
    room: tuple[float, float, float] = (10.0, 6.0, 4.0)
    dt: float = 0.25
    substeps: int = 4
    camera_rate_hz: float = 1.0
    n_cameras: int = 2
    camera_knock_deg: float = 0.0
    pixel_noise: float = 1.0
    camera_mode: str = "closed_form"
    image_noise: float = 4.0
    params: BlimpParams = field(default_factory=BlimpParams)
    randomize: float = 0.0
    weights: RewardWeights = field(default_factory=RewardWeights)
    reality: str = "lab"
    reality_strength: float | None = None

    def __post_init__(self) -> None:
        check_preset(self.reality)
        if self.reality_strength is not None:
            check_strength(self.reality_strength)
        if self.task not in TASKS:
            raise ValueError(f"task must be one of {TASKS}, got {self.task!r}")
        if not (self.dt > 0 and math.isfinite(self.dt)):
            raise ValueError(f"dt must be a positive number, got {self.dt!r}")
        if self.substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {self.substeps!r}")
        if not 0 < self.camera_rate_hz <= 1.0 / self.dt + 1e-9:
            raise ValueError(f"camera_rate_hz must be in (0, 1/dt], got {self.camera_rate_hz!r}")
        if self.camera_mode not in ("closed_form", "rendered"):
            raise ValueError(f"camera_mode must be 'closed_form' or 'rendered', got {self.camera_mode!r}")
        if not (math.isfinite(self.camera_knock_deg) and abs(self.camera_knock_deg) <= MAX_KNOCK_DEG):
            raise ValueError(f"camera_knock_deg must be in [-{MAX_KNOCK_DEG}, {MAX_KNOCK_DEG}], "
                             f"got {self.camera_knock_deg!r}")  # fmt: skip
        if self.pixel_noise < 0:
            raise ValueError(f"pixel_noise must be >= 0, got {self.pixel_noise!r}")
        steps = 1.0 / (self.camera_rate_hz * self.dt)
        if abs(steps - round(steps)) > 1e-6:
            raise ValueError("1 / (camera_rate_hz * dt) must be a whole number of env steps")

    @property
    def cameras(self) -> tuple[Camera, ...]:
        """The wall cameras."""
        return _cameras(self.room, self.camera_rate_hz, self.n_cameras, self.camera_knock_deg)

    @property
    def semi_axes(self) -> tuple[float, float, float]:
        """Envelope semi-axes (m)."""
        p = self.params
        return (p.semi_length, p.semi_diameter, p.semi_diameter)

    @property
    def noise_size(self) -> int:
        """Normal draws per env step: 3 gust + ``n_cameras * K * 2`` pixel noise."""
        return 3 + self.n_cameras * N_BOUNDARY * 2

    def frame_schedule(self, step: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Which cameras deliver a frame at env step ``step`` (N,) -> (N, C) bool."""
        period = round(1.0 / (self.camera_rate_hz * self.dt))
        offsets = np.array([round(c.phase_s / self.dt) for c in self.cameras])
        return (np.asarray(step)[:, None] - offsets[None, :]) % period == 0

    @cached_property
    def ellipse_bounds(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Lower and upper bounds ``(C, 5)`` of the reported ellipses."""
        w, h = self.cameras[0].size
        c = self.n_cameras
        low = np.tile(np.array([0, 0, 0, 0, -math.pi / 2], dtype=np.float32), (c, 1))
        high = np.tile(np.array([w - 1, h - 1, 2 * w, 2 * w, math.pi / 2], dtype=np.float32), (c, 1))
        return low, high

    def observation_space(self) -> spaces.Dict:
        """``{"ellipses": Box(C, 5) float32, "valid": MultiBinary(C)}``."""
        low, high = self.ellipse_bounds
        return spaces.Dict(
            {
                "ellipses": spaces.Box(low, high, dtype=np.float32),
                "valid": spaces.MultiBinary(self.n_cameras),
            }
        )

    @property
    def strength(self) -> float:
        """The reality strength in force (the preset's unless overridden)."""
        if self.reality_strength is None:
            return check_preset(self.reality).strength
        return float(self.reality_strength)

    @cached_property
    def world_params(self) -> BlimpParams:
        """``params`` with the preset's draft level: the episodes' nominal parameters."""
        scale = check_preset(self.reality).draft_scale
        if scale == 1.0:
            return self.params
        return dataclasses.replace(self.params, gust_std=self.params.gust_std * scale)

    @property
    def track_depth(self) -> int:
        """Env steps of past poses kept for motion capture and camera latency."""
        p, k = self.params, 1.0 + self.randomize
        lag = max(MOCAP_SAMPLES / MOCAP_RATE_HZ, self.strength * k * (p.camera_latency + 4 * p.camera_jitter))
        return math.ceil(lag / self.dt) + 1

    def draw_params(self, rng: np.random.Generator) -> BlimpParams:
        """The episode's physical parameters (randomised when ``randomize > 0``)."""
        if self.randomize > 0:
            return randomize_params(self.world_params, rng, self.randomize)
        return self.world_params

    def map_action(self, action: FloatArray, params: BlimpParams) -> FloatArray:
        """Normalised actions ``(N, 3)`` in [-1, 1] to motor commands (N, thrust rad, N)."""
        scale = np.array([params.max_main_thrust, params.max_vector_angle, params.max_tail_thrust])
        return np.clip(action, -1.0, 1.0) * scale

    def out_of_bounds(self, position: FloatArray) -> NDArray[np.bool_]:
        """Blimps ``(N, 3)`` that left the room or touched the floor or ceiling."""
        lx, ly, lz = self.room
        b = self.params.semi_diameter
        x, y, z = position.T
        return (x < 0) | (x > lx) | (y < 0) | (y > ly) | (z - b < 0) | (z + b > lz)


_CAMERA_CACHE: dict[tuple, tuple[Camera, ...]] = {}


def _cameras(
    room: tuple[float, float, float], rate: float, n: int, knock_deg: float = 0.0
) -> tuple[Camera, ...]:
    key = (room, rate, n, knock_deg)
    if key not in _CAMERA_CACHE:  # cameras cache their pixel rays: build them once
        cams = default_cameras(room, rate, n)
        _CAMERA_CACHE[key] = (knocked(cams[0], knock_deg), *cams[1:]) if knock_deg else cams
    return _CAMERA_CACHE[key]


def knocked(camera: Camera, degrees: float) -> Camera:
    """``camera`` panned by ``degrees`` about the world's vertical (its position kept)."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # world vectors turned about z
    return dataclasses.replace(camera, rotation=camera.rotation @ turn.T)


def camera_lag(cfg: WorldConfig, params: BlimpParams) -> tuple[float, float]:
    """Camera latency and its jitter (s) of a blimp with ``params`` in world ``cfg``."""
    if cfg.strength == 0:
        return 0.0, 0.0
    effects = lab_effects(params, cfg.strength)
    return effects.latency, effects.jitter


def check_action(action: object, n: int | None = None) -> FloatArray:
    """Validate an action: shape ``(3,)`` (or ``(n, 3)``) and finite, else ``ValueError``."""
    arr = np.asarray(action, dtype=np.float64)
    expected = (3,) if n is None else (n, 3)
    if arr.shape != expected:
        raise ValueError(f"action must have shape {expected}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"action must be finite, got {arr.tolist()}")
    return arr


def initial_state(rng: np.random.Generator, room: tuple[float, float, float]) -> FloatArray:
    """A random start ``(12,)``: central position, any yaw, small roll and pitch, at rest."""
    lx, ly, lz = room
    pos = rng.uniform([2.0, 1.5, 1.0], [lx - 2.0, ly - 1.5, lz - 1.2])
    att = np.array([rng.normal(0, 0.05), rng.normal(0, 0.05), rng.uniform(-math.pi, math.pi)])
    return np.concatenate([pos, att, np.zeros(6)])


def observe(
    cfg: WorldConfig,
    state: FloatArray,
    frames: NDArray[np.bool_],
    noise: FloatArray,
    rngs: Sequence[np.random.Generator] = (),
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Camera ellipses of ``N`` blimps.

    Parameters
    ----------
    state: (N, >= 6)
        Each blimp's pose ``(x, y, z, roll, pitch, yaw)`` when the frames were exposed
        (further columns are ignored).
    frames: (N, C) bool
        Cameras delivering a frame this step.
    noise: (N, C * K * 2)
        Standard-normal draws, scaled here by ``cfg.pixel_noise``.
    rngs
        One generator per blimp for the image noise of the rendered mode.

    Returns
    -------
    ellipses: (N, C, 5) float32, zero where not valid
    valid: (N, C) int8
    """
    n, c = frames.shape
    ell = np.zeros((n, c, 5))
    valid = np.zeros((n, c), dtype=bool)
    rows = np.flatnonzero(frames.any(axis=1))
    if rows.size:
        rot = euler_to_matrix(state[rows, 3:6])
        if cfg.camera_mode == "rendered":
            e, vis = _rendered(cfg, state[rows, :3], rot, frames[rows], [rngs[i] for i in rows])
        else:
            px = cfg.pixel_noise * noise[rows].reshape(rows.size, c, N_BOUNDARY, 2)
            e, vis = outline_ellipses(cfg.cameras, state[rows, :3], rot, cfg.semi_axes, px)
        ell[rows], valid[rows] = e, vis & frames[rows]
    ell[~valid] = 0.0
    low, high = cfg.ellipse_bounds
    ell32 = np.clip(ell.astype(np.float32), low, high)
    return ell32, valid.astype(np.int8)


def _rendered(
    cfg: WorldConfig,
    position: FloatArray,
    rotation: FloatArray,
    frames: NDArray[np.bool_],
    rngs: Sequence[np.random.Generator],
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """The slow camera mode: render each due frame, subtract the background, fit."""
    out = np.zeros((*frames.shape, 5))
    vis = np.zeros(frames.shape, dtype=bool)
    for i, k in zip(*np.nonzero(frames), strict=True):  # one image per frame: inherently slow
        cam = cfg.cameras[k]
        img = render_frame(cam, position[i], rotation[i], cfg.semi_axes, rngs[i], cfg.image_noise)
        fit = fit_ellipse_image(cam, img)
        w, h = cam.size
        if fit is not None and 0 <= fit[0] <= w - 1 and 0 <= fit[1] <= h - 1:
            out[i, k], vis[i, k] = fit, True
    return out, vis
