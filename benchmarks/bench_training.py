"""GP training speed: what the one-thread, potri and subset choices buy on this machine.

Paper sizes: n = 900 points, d = 16 inputs (the blimp's 12-D state with yaw as cos/sin, plus
3 controls), m = 50 pseudo-inputs. Measured in one run:

1. One exact negative-log-marginal-likelihood evaluation (value and gradient) with the
   BLAS library's default threads vs one thread (training pins one thread).
2. ``K^-1`` from the Cholesky factor: LAPACK ``potri`` vs solving with the identity.
3. One sparse (FITC) evaluation, default threads vs one thread.
4. ``fit_exact`` on 2 outputs: hyperparameters on all points vs on a 300-point subset
   then polished on all (``hyper_points``), with the held-out RMS of both fits.

The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import scipy.linalg as sla
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).parent))
from machine import best_time, limits

from estimator_service.gp import exact_nll, fit_exact, sparse_nll
from estimator_service.gp.linalg import chol_inverse

N, D, M = 900, 16, 50


def data(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    x = rng.normal(size=(n, D))
    y = np.stack([np.sin(x[:, 0]) + 0.5 * x[:, 1] * x[:, 2], np.cos(x[:, 3]) * x[:, 4]], axis=1)
    return x, y + 0.05 * rng.normal(size=y.shape)


def main() -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats and optimiser iterations")
    args = ap.parse_args()
    reps, iters = (3, 30) if args.quick else (10, 60)
    rng = np.random.default_rng(0)
    x, y = data(rng, N)
    theta = np.concatenate([np.full(D, np.log(3.0)), [0.0, np.log(0.1)]])
    prm = np.concatenate([theta, x[:M].ravel()])
    t = {}
    for threads in (None, 1):
        with threadpool_limits(threads):
            key = "default" if threads is None else "1thread"
            t[f"exact_{key}"] = best_time(lambda: exact_nll(theta, x, y[:, 0]), reps)
            t[f"sparse_{key}"] = best_time(lambda: sparse_nll(prm, x, y[:, 0], M), reps)
    a = rng.normal(size=(N, N))
    lo = np.linalg.cholesky(a @ a.T + N * np.eye(N))
    t["potri"] = best_time(lambda: chol_inverse(lo), reps)
    t["solve_identity"] = best_time(lambda: sla.cho_solve((lo, True), np.eye(N)), reps)
    xt, yt = data(rng, 500)
    fits = {}
    for name, hp in (("all_points", None), ("subset_300", 300)):
        t0 = time.perf_counter()
        gp = fit_exact(x, y, restarts=1, max_iter=iters, rng=np.random.default_rng(1), hyper_points=hp)
        fits[name] = (time.perf_counter() - t0, float(np.sqrt(np.mean((gp.predict(xt).mean - yt) ** 2))))
    for k, v in t.items():
        print(f"{k:>18}: {v * 1e3:8.2f} ms")
    for k, (s, rms) in fits.items():
        print(f"fit_exact {k:>10}: {s:6.1f} s, held-out RMS {rms:.4f}")
    result = {
        "exact_nll_ms_default_threads": round(t["exact_default"] * 1e3, 2),
        "exact_nll_ms_one_thread": round(t["exact_1thread"] * 1e3, 2),
        "sparse_nll_ms_default_threads": round(t["sparse_default"] * 1e3, 2),
        "sparse_nll_ms_one_thread": round(t["sparse_1thread"] * 1e3, 2),
        "potri_speedup": round(t["solve_identity"] / t["potri"], 2),
        "subset_fit_speedup": round(fits["all_points"][0] / fits["subset_300"][0], 2),
        "subset_to_full_rms_ratio": round(fits["subset_300"][1] / fits["all_points"][1], 3),
    }
    result.update(limits())  # this machine's dgemm rate and read bandwidth, for the ratios
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
