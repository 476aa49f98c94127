"""Process-noise calibration: a prediction model whose noise variance is scaled.

A GP's predictive variance (and the parametric model's residual variance) describes
one-step errors of independent transitions. A filter chains them, and unmodelled effects
that persist over many steps (on the simulated blimp: wind gusts with a 3 s correlation
time) make every filter overconfident. One scalar per model kind, chosen on training
flights so that the filter's average NEES matches the state dimension, corrects that
(:func:`agents.training.calibrate_noise`); it is stored beside the models in
``calibration.json`` and applied by :func:`estimator_service.factory.load_models`.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from estimator_service.gp.io import atomic_write_text
from estimator_service.models.base import ModelOutput, PredictionModel

__all__ = ["CALIBRATION_FILE", "NoiseScaledPrediction", "read_noise_scales", "write_noise_scales"]

FloatArray = NDArray[np.float64]
CALIBRATION_FILE = "calibration.json"


@dataclass(frozen=True)
class NoiseScaledPrediction:
    """``inner`` with its noise variance multiplied by ``scale`` (mean and Jacobian as is)."""

    inner: PredictionModel
    scale: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"noise scale must be finite and > 0, got {self.scale!r}")

    @property
    def state_dim(self) -> int:
        return self.inner.state_dim

    @property
    def control_dim(self) -> int:
        return self.inner.control_dim

    def predict(self, x: FloatArray, u: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        """``inner.predict`` with ``var * scale``: mean ``(M, n)``, var ``(M, n)``, jac ``(M, n, n)``."""
        out = self.inner.predict(x, u, jac=jac, var=var)
        return ModelOutput(out.mean, out.var * self.scale, out.jac)


def read_noise_scales(folder: str | os.PathLike[str]) -> dict[str, float]:
    """``{model kind: scale}`` from ``folder/calibration.json`` (empty when there is none)."""
    path = Path(folder) / CALIBRATION_FILE
    if not path.exists():
        return {}
    try:
        raw = json.loads(path.read_text())
        scales = {str(k): float(v) for k, v in raw["noise_scale"].items()}
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise ValueError(f"{os.fspath(path)!r}: expected {{'noise_scale': {{kind: number}}}} ({e})") from e
    bad = {k: v for k, v in scales.items() if not (math.isfinite(v) and v > 0)}
    if bad:
        raise ValueError(f"{os.fspath(path)!r}: noise scales must be finite and > 0, got {bad}")
    return scales


def write_noise_scales(folder: str | os.PathLike[str], scales: dict[str, float], **details: object) -> Path:
    """Merge ``scales`` into ``folder/calibration.json`` (written to a temporary file, then renamed)."""
    path = Path(folder) / CALIBRATION_FILE
    merged = {**read_noise_scales(folder), **{k: float(v) for k, v in scales.items()}}
    old = json.loads(path.read_text()).get("details", {}) if path.exists() else {}
    text = json.dumps({"noise_scale": merged, "details": {**old, **details}}, indent=2, default=_plain)
    return atomic_write_text(path, text)


def _plain(o: object) -> object:
    return o.tolist() if isinstance(o, np.ndarray) else float(o)  # type: ignore[arg-type]
