"""Gaussian-process regression for prediction and observation models."""

from estimator_service.gp.base import GPModel, GPPrediction, Progress, Scaler
from estimator_service.gp.exact import ExactGP, exact_nll, fit_exact

__all__ = ["ExactGP", "GPModel", "GPPrediction", "Progress", "Scaler", "exact_nll", "fit_exact"]
