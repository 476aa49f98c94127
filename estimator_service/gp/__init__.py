"""Gaussian-process regression for prediction and observation models.

Four kinds, one batched interface (:class:`GPModel.predict` -> :class:`GPPrediction`):
:class:`ExactGP` (:func:`fit_exact`), :class:`SparseGP` (:func:`fit_sparse`),
:class:`HeteroscedasticGP` (:func:`fit_hetero`) and :class:`EnhancedGP`
(:func:`fit_enhanced`); :class:`CircularGP` (:func:`fit_circular`) wraps any of them so that
angles enter and leave on the circle. :func:`save_gp` / :func:`load_gp` persist any of them.
"""

from estimator_service.gp.base import GPModel, GPPrediction, Progress, Scaler
from estimator_service.gp.circular import CircularGP, fit_circular
from estimator_service.gp.enhanced import EnhancedGP, fit_enhanced, numeric_jacobian
from estimator_service.gp.exact import ExactGP, fit_exact
from estimator_service.gp.hetero import HeteroscedasticGP, fit_hetero
from estimator_service.gp.hyper import exact_nll
from estimator_service.gp.io import FORMAT_VERSION, ModelFileError, load_gp, load_innermost_gp, save_gp
from estimator_service.gp.sparse import SparseGP, fit_sparse, sparse_nll

__all__ = [
    "FORMAT_VERSION",
    "CircularGP",
    "EnhancedGP",
    "ExactGP",
    "GPModel",
    "GPPrediction",
    "HeteroscedasticGP",
    "ModelFileError",
    "Progress",
    "Scaler",
    "SparseGP",
    "exact_nll",
    "fit_circular",
    "fit_enhanced",
    "fit_exact",
    "fit_hetero",
    "fit_sparse",
    "load_gp",
    "load_innermost_gp",
    "numeric_jacobian",
    "save_gp",
    "sparse_nll",
]
