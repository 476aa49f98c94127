"""The paper's GP set-up for Table 10: a GP toolbox's defaults, beside our ARD GPs.

Ko & Fox used a GP toolbox with its defaults: one GP per output, an isotropic squared
exponential kernel plus a bias and white noise, on the raw (unscaled) inputs. Here the
bias kernel's role (an unknown constant level) is played by centring each output; inputs
are not scaled, and one length scale is shared by all input dimensions. Hyperparameters
maximise the marginal likelihood (the ARD GP's :func:`~estimator_service.gp.hyper.exact_nll`
with its length-scale gradient summed over the tied dimensions), so the posterior is an
ordinary :class:`~estimator_service.gp.exact.ExactGP` the filters use unchanged.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize

from estimator_service.gp.base import Scaler
from estimator_service.gp.exact import ExactGP
from estimator_service.gp.hyper import exact_nll

__all__ = ["fit_isotropic"]

FloatArray = NDArray[np.float64]


def _tied_nll(z: FloatArray, x: FloatArray, y: FloatArray) -> tuple[float, FloatArray]:
    """NLL and gradient for ``z = [log ell, log sf, log sn]`` with ``ell`` shared by all inputs."""
    d = x.shape[1]
    nll, grad = exact_nll(np.concatenate([np.full(d, z[0]), z[1:]]), x, y)
    return nll, np.concatenate([[grad[:d].sum()], grad[d:]])


def fit_isotropic(x: FloatArray, y: FloatArray, rng: np.random.Generator, restarts: int = 1) -> ExactGP:
    """One isotropic GP per output column of ``y (n, P)`` on raw inputs ``x (n, d)``.

    As a toolbox user would: one optimisation from unit length scale, the output's spread
    and a tenth of it as noise (further restarts from random multiples of those; the best
    likelihood is kept).
    """
    y = y.reshape(len(y), -1)
    xsc = Scaler(np.zeros(x.shape[1]), np.ones(x.shape[1]))
    ysc = Scaler(y.mean(axis=0), np.ones(y.shape[1]))
    yc = ysc.apply(y)
    thetas = []
    for p in range(y.shape[1]):
        sd = float(yc[:, p].std()) or 1.0
        base = np.log([1.0, sd, 0.1 * sd])
        best = None
        for k in range(restarts):
            start = base + (rng.normal(0.0, 1.0, 3) if k else 0.0)
            res = minimize(_tied_nll, start, args=(x, yc[:, p]), jac=True, method="L-BFGS-B",
                           bounds=[(-9.0, 9.0)] * 3, options={"maxiter": 200})  # fmt: skip
            best = res if best is None or res.fun < best.fun else best
        assert best is not None
        thetas.append(np.concatenate([np.full(x.shape[1], best.x[0]), best.x[1:]]))
    return ExactGP.from_theta(x, yc, np.array(thetas), xsc, ysc)
