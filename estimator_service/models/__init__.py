"""Prediction and observation models: the interface filters depend on, and implementations."""

from estimator_service.models.base import (
    LinearGaussianObservation,
    LinearGaussianPrediction,
    ModelOutput,
    ObservationModel,
    PredictionModel,
)
from estimator_service.models.gp_models import GPObservationModel, GPPredictionModel

__all__ = [
    "GPObservationModel",
    "GPPredictionModel",
    "LinearGaussianObservation",
    "LinearGaussianPrediction",
    "ModelOutput",
    "ObservationModel",
    "PredictionModel",
]
