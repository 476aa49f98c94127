"""Wire protocol of the estimator service (see ``docs/protocol.md``).

Encoding: MessagePack maps. It is compact, fast in Python (a C extension) and has
libraries in every language a robot stack uses; float64 values travel bit-exactly, which
the lock-step mode needs. Arrays may be lists of numbers or ``bin`` fields of row-major
little-endian float64 (beliefs use the latter: no per-number objects to build or parse).
Every message carries ``v`` (:data:`PROTOCOL_VERSION`),
``seq`` (int) and ``t`` (seconds, sim or wall time).

Decoding validates everything and raises :class:`ProtocolError` naming the field and the
problem; nothing is applied from a message that fails.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
import zenoh
from numpy.typing import NDArray

__all__ = [
    "ENCODING",
    "MAX_PAYLOAD",
    "MSGPACK",
    "NO_SESSION",
    "PROTOCOL_VERSION",
    "Camera",
    "Control",
    "ProtocolError",
    "RepeatedStep",
    "Reset",
    "Step",
    "decode",
    "encode",
    "encode_belief",
    "pack_array",
    "parse_camera",
    "parse_control",
    "parse_reset",
    "parse_step",
    "unpack_array",
]

PROTOCOL_VERSION = 2  # 2: arrays may travel as little-endian float64 bytes; beliefs do
MAX_PAYLOAD = 64 * 1024  # bytes; anything larger is rejected unread (in the zenoh callback)
NO_SESSION = "no session for blimp"  # how every error about a missing session starts
ENCODING = "application/msgpack"  # the zenoh encoding every payload is tagged with
MAX_CAMERAS = 16
MAX_ABS = 1e12  # no input number (control, sensor value, mean, spread) is larger in magnitude
FILTERS = ("ekf", "ukf", "pf")
MODELS = ("param", "gp", "egp", "hetgp", "sparse")
FloatArray = NDArray[np.float64]


MSGPACK = zenoh.Encoding(ENCODING)


class RepeatedStep(Exception):
    """A ``step`` query sent again with the ``seq`` and ``t`` of the session's last step (a
    client retrying after a time-out): answered with the same reply, nothing recomputed."""

    def __init__(self, reply: bytes) -> None:
        super().__init__("repeated step")
        self.reply = reply


class ProtocolError(ValueError):
    """A message that cannot be applied; the text names the field and the problem."""


def encode(message: dict[str, Any]) -> bytes:
    return msgpack.packb(message, use_bin_type=True)


def decode(payload: bytes) -> dict[str, Any]:
    """Bytes to a message map with a supported version."""
    if len(payload) > MAX_PAYLOAD:
        raise ProtocolError(f"payload of {len(payload)} bytes exceeds the {MAX_PAYLOAD}-byte cap")
    try:
        msg = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except Exception as exc:  # any malformed byte string
        raise ProtocolError(f"undecodable payload: not MessagePack ({type(exc).__name__})") from exc
    if not isinstance(msg, dict):
        raise ProtocolError(f"message must be a map, got {type(msg).__name__}")
    if msg.get("v") != PROTOCOL_VERSION:
        raise ProtocolError(
            f"field 'v': protocol version {msg.get('v')!r} unsupported, expected {PROTOCOL_VERSION}"
        )
    return msg


def _field(msg: dict[str, Any], name: str) -> Any:
    if name not in msg:
        raise ProtocolError(f"missing field '{name}'")
    return msg[name]


def _number(msg: dict[str, Any], name: str, integer: bool = False) -> float:
    val = _field(msg, name)
    ok = isinstance(val, int) if integer else isinstance(val, (int, float))
    if isinstance(val, bool) or not ok:
        raise ProtocolError(f"field '{name}' must be {'an integer' if integer else 'a number'}")
    if not math.isfinite(val):
        raise ProtocolError(f"field '{name}' must be finite")
    return val


def _vector(val: Any, name: str, size: int) -> FloatArray:
    if isinstance(val, bytes):  # packed little-endian float64 (what beliefs use)
        if len(val) != 8 * size:
            raise ProtocolError(
                f"field '{name}' must hold {size} little-endian float64 ({8 * size} bytes), "
                f"got {len(val)} bytes"
            )
        return _plausible(np.frombuffer(val, dtype="<f8").astype(np.float64), name)
    if not isinstance(val, (list, tuple)) or len(val) != size:
        got = len(val) if isinstance(val, (list, tuple)) else type(val).__name__
        raise ProtocolError(f"field '{name}' must be a list of {size} numbers, got {got}")
    if all((type(x) is float or type(x) is int) and -MAX_ABS <= x <= MAX_ABS for x in val):
        return np.array(val, dtype=np.float64)  # plausible numbers (NaN fails the comparison)
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in val):
        raise ProtocolError(f"field '{name}' must contain numbers only")
    return _plausible(np.asarray(val, dtype=np.float64), name)


def _plausible(arr: FloatArray, name: str) -> FloatArray:
    if not np.isfinite(arr).all():
        raise ProtocolError(f"field '{name}' contains NaN or Inf")
    if (np.abs(arr) > MAX_ABS).any():
        raise ProtocolError(f"field '{name}' has a value beyond +-{MAX_ABS:g}")
    return arr


@dataclass(frozen=True)
class Control:
    seq: int
    t: float
    u: FloatArray


@dataclass(frozen=True)
class Camera:
    seq: int
    t: float
    camera: int
    ellipse: FloatArray | None  # None: the camera saw nothing


@dataclass(frozen=True)
class Step:
    """Lock-step input: predict with ``u``, then update with ``frames`` (camera -> ellipse)."""

    seq: int
    t: float
    u: FloatArray
    frames: dict[int, FloatArray]


@dataclass(frozen=True)
class Reset:
    seq: int
    t: float
    mean: FloatArray
    cov: FloatArray
    filter: str | None
    model: str | None
    seed: int


def _header(msg: dict[str, Any]) -> tuple[int, float]:
    return int(_number(msg, "seq", integer=True)), float(_number(msg, "t"))


def parse_control(msg: dict[str, Any], n_controls: int = 3) -> Control:
    seq, t = _header(msg)
    return Control(seq, t, _vector(_field(msg, "u"), "u", n_controls))


def _camera_index(val: Any, name: str, n_cameras: int) -> int:
    if isinstance(val, bool) or not isinstance(val, int) or not 0 <= val < min(n_cameras, MAX_CAMERAS):
        raise ProtocolError(f"field '{name}' must be a camera index in 0..{n_cameras - 1}, got {val!r}")
    return val


def parse_camera(msg: dict[str, Any], camera: int, sizes: Sequence[int]) -> Camera:
    """A ``camera/<k>`` input; ``sizes[k]`` is the number of values sensor ``k`` reports
    (the blimp's cameras: 5, an ellipse)."""
    seq, t = _header(msg)
    ell = _field(msg, "ellipse")
    k = _camera_index(camera, "camera", len(sizes))
    return Camera(seq, t, k, None if ell is None else _vector(ell, "ellipse", sizes[k]))


def parse_step(msg: dict[str, Any], sizes: Sequence[int], n_controls: int = 3) -> Step:
    """A ``step`` query; ``sizes`` as for :func:`parse_camera`."""
    seq, t = _header(msg)
    u = _vector(_field(msg, "u"), "u", n_controls)
    frames_in = _field(msg, "frames")
    if not isinstance(frames_in, list) or len(frames_in) > len(sizes):
        raise ProtocolError(f"field 'frames' must be a list of at most {len(sizes)} [camera, ellipse] pairs")
    frames: dict[int, FloatArray] = {}
    for i, item in enumerate(frames_in):
        if not isinstance(item, (list, tuple)) or len(item) != 2:
            raise ProtocolError(f"field 'frames[{i}]' must be a [camera, ellipse] pair")
        k = _camera_index(item[0], f"frames[{i}][0]", len(sizes))
        if k in frames:
            raise ProtocolError(f"field 'frames': camera {k} given twice")
        frames[k] = _vector(item[1], f"frames[{i}][1]", sizes[k])
    return Step(seq, t, u, frames)


def parse_reset(msg: dict[str, Any], state_dim: int = 12) -> Reset:
    seq, t = _header(msg)
    mean = _vector(_field(msg, "mean"), "mean", state_dim)
    if "cov" in msg:
        cov = _vector(msg["cov"], "cov", state_dim * state_dim).reshape(state_dim, state_dim)
        if not np.allclose(cov, cov.T) or np.linalg.eigvalsh(0.5 * (cov + cov.T))[0] <= 0:
            raise ProtocolError("field 'cov' must be symmetric positive definite")
    else:
        std = _vector(_field(msg, "std"), "std", state_dim)
        if np.any(std <= 0):
            raise ProtocolError("field 'std' must be positive")
        cov = np.diag(std * std)
    filt, model = msg.get("filter"), msg.get("model")
    if filt is not None and filt not in FILTERS:
        raise ProtocolError(f"field 'filter' must be one of {FILTERS}, got {filt!r}")
    if model is not None and model not in MODELS:
        raise ProtocolError(f"field 'model' must be one of {MODELS}, got {model!r}")
    seed = msg.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ProtocolError("field 'seed' must be a non-negative integer")
    return Reset(seq, t, mean, cov, filt, model, seed)


def encode_belief(
    blimp: str,
    seq: int,
    t: float,
    mean: FloatArray,
    cov: FloatArray,
    filter_name: str,
    model: str,
    nis: float,
    dof: int,
    diverged: bool,
    step_ms: float,
    service: str = "",
) -> bytes:
    """The belief message: mean, covariance (row-major, packed float64), the step report and
    the id of the service that computed it."""
    return encode(
        {
            "service": service,
            "v": PROTOCOL_VERSION,
            "blimp": blimp,
            "seq": int(seq),
            "t": float(t),
            "mean": pack_array(mean),
            "cov": pack_array(cov),
            "filter": filter_name,
            "model": model,
            "nis": None if math.isnan(nis) else float(nis),
            "dof": int(dof),
            "diverged": bool(diverged),
            "step_ms": float(step_ms),
        }
    )


def pack_array(a: FloatArray) -> bytes:
    """An array as row-major little-endian float64 bytes (a MessagePack ``bin``)."""
    return np.ascontiguousarray(a, dtype="<f8").tobytes()


def unpack_array(val: bytes | list, shape: tuple[int, ...]) -> FloatArray:
    """Inverse of :func:`pack_array` (lists of numbers are accepted too)."""
    if isinstance(val, bytes):
        return np.frombuffer(val, dtype="<f8").astype(np.float64).reshape(shape)
    return np.asarray(val, dtype=np.float64).reshape(shape)


def decode_belief(payload: bytes) -> dict[str, Any]:
    """Belief message with ``mean (n,)`` and ``cov (n, n)`` as arrays."""
    msg = decode(payload)
    mean = msg["mean"]
    n = len(mean) // 8 if isinstance(mean, bytes) else len(mean)
    msg["mean"] = unpack_array(mean, (n,))
    msg["cov"] = unpack_array(msg["cov"], (n, n))
    return msg
