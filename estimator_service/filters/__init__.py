"""GP-BayesFilters: GP-EKF, GP-UKF and GP-PF over any prediction/observation models."""

from estimator_service.filters.common import (
    GaussianBelief,
    ParticleBelief,
    StepInfo,
    Wrapping,
    make_pd,
)
from estimator_service.filters.kalman import EKF, UKF, sigma_weights
from estimator_service.filters.particle import PF, systematic_resample

__all__ = [
    "EKF",
    "PF",
    "UKF",
    "GaussianBelief",
    "ParticleBelief",
    "StepInfo",
    "Wrapping",
    "make_pd",
    "sigma_weights",
    "systematic_resample",
]
