"""GP-BayesFilters: GP-EKF, GP-UKF and GP-PF over any prediction/observation models."""

from estimator_service.filters.common import (
    GaussianBelief,
    ParticleBelief,
    StepInfo,
    Wrapping,
    make_pd,
)
from estimator_service.filters.kalman import EKF, UKF, sigma_weights, unscented_transform
from estimator_service.filters.particle import PF, systematic_resample
from estimator_service.filters.policy import step_many, step_one, update_many

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
    "step_many",
    "step_one",
    "systematic_resample",
    "unscented_transform",
    "update_many",
]
