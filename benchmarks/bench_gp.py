"""Batched GP prediction speed vs the machine's matmul peak and vs scikit-learn.

Sizes from the paper's blimp (Sect. 6): n = 900 training points, d = 15 inputs (12-D state
+ 3 controls), P = 12 outputs, M = 2,000 queries (a GP-PF step). Float64 throughout.

Prints the achieved GFLOP/s next to this machine's own matrix-multiply GFLOP/s and read
bandwidth measured in the same run (``benchmarks/machine.py``), the ratio of our time to
the flop-count limit (target <= 1.5), the one-query time over the bandwidth limit of its
factors (target <= 2), the speed-up
over ``sklearn.gaussian_process.GaussianProcessRegressor.predict(return_std=True)`` with
the same hyperparameters (target >= 3), and the one-query (EKF) and 25-query (UKF)
latencies (targets 0.2 ms and 1 ms). The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
from machine import best_time, dgemm_gflops, read_gbs, triangular_bytes
from threadpoolctl import threadpool_limits

from estimator_service.gp import ExactGP, Scaler

N, D, P, M = 900, 15, 12, 2000


def build_gp(rng: np.random.Generator) -> tuple[ExactGP, np.ndarray, np.ndarray, np.ndarray]:
    x = rng.normal(size=(N, D))
    y = np.tanh(x[:, :P] + 0.3 * x[:, P - 1 : 2 * P - 1].sum(axis=1, keepdims=True))
    theta = np.concatenate(
        [
            rng.uniform(math.log(2.0), math.log(6.0), (P, D)),
            np.zeros((P, 1)),
            np.full((P, 1), math.log(0.1)),
        ],
        axis=1,
    )
    ident = (Scaler(np.zeros(D), np.ones(D)), Scaler(np.zeros(P), np.ones(P)))
    gp = ExactGP.from_theta(x, y, theta, *ident)
    return gp, x, y, theta


def sklearn_predict(x: np.ndarray, y: np.ndarray, theta: np.ndarray, q: np.ndarray):
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    models = []
    for p in range(P):
        kern = ConstantKernel(math.exp(2 * theta[p, -2]), "fixed") * RBF(
            np.exp(theta[p, :D]), "fixed"
        ) + WhiteKernel(math.exp(2 * theta[p, -1]), "fixed")
        models.append(GaussianProcessRegressor(kern, alpha=1e-12, optimizer=None).fit(x, y[:, p]))

    def run() -> tuple[np.ndarray, np.ndarray]:
        outs = [m.predict(q, return_std=True) for m in models]
        return np.stack([o[0] for o in outs], 1), np.stack([o[1] ** 2 for o in outs], 1)

    return run


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="fewer repetitions")
    args = parser.parse_args(argv)
    reps = 2 if args.quick else 5
    rng = np.random.default_rng(0)
    gp, x, y, theta = build_gp(rng)
    q = rng.normal(size=(M, D))
    mm, bw = dgemm_gflops(reps), read_gbs(reps)
    t_mv = best_time(lambda: gp.predict(q), reps)
    t_mj = best_time(lambda: gp.predict(q, return_var=False, return_jac=True), reps)
    flops = P * (N * N * M + 2 * M * N * D + 2 * M * N)  # triangular solves dominate
    limit = flops / (mm * 1e9)
    sk = sklearn_predict(x, y, theta, q)
    t_sk = best_time(sk, 1 if args.quick else 2)
    sk_mean, sk_var = sk()
    ours = gp.predict(q)
    err = max(np.abs(ours.mean - sk_mean).max(), np.abs(ours.var - sk_var).max())
    lat = {}
    for threads in (1, 2):
        with threadpool_limits(threads):
            for k in (1, 25):
                lat[(threads, k)] = best_time(lambda k=k: gp.predict(q[:k]), 50 if args.quick else 200)
            lat[(threads, "mean1")] = best_time(lambda: gp.predict(q[:1], return_var=False), 200)
    best1 = min(lat[(1, 1)], lat[(2, 1)])
    best25 = min(lat[(1, 25)], lat[(2, 25)])
    bw_limit = triangular_bytes(N, P) / (bw * 1e9)  # one query reads every output's factor once
    print(f"n={N} d={D} P={P} M={M}  float64")
    print(f"matmul peak (2000^3):         {mm:8.1f} GFLOP/s   read bandwidth {bw:6.2f} GB/s")
    print(f"batch mean+var:               {t_mv * 1e3:8.1f} ms  {flops / t_mv / 1e9:6.1f} GFLOP/s  "
          f"{t_mv / limit:4.2f}x flop-count limit ({limit * 1e3:.0f} ms)")  # fmt: skip
    print(f"batch mean+Jacobian:          {t_mj * 1e3:8.1f} ms")
    print(f"sklearn predict(return_std):  {t_sk * 1e3:8.1f} ms  -> speed-up {t_sk / t_mv:5.1f}x "
          f"(max |diff| {err:.1e})")  # fmt: skip
    for (threads, k), t in lat.items():
        print(f"  {threads} BLAS thread(s), {k!s:>5} queries: {t * 1e3:7.3f} ms")
    print(f"one query: {best1 * 1e3:.3f} ms = {best1 / bw_limit:.2f}x the bandwidth limit "
          f"({triangular_bytes(N, P) / 1e6:.0f} MB of factors: {bw_limit * 1e3:.3f} ms)")  # fmt: skip
    result = {
        "batch_mean_var_s": round(t_mv, 4),
        "batch_mean_jac_s": round(t_mj, 4),
        "achieved_gflops": round(flops / t_mv / 1e9, 1),
        "matmul_gflops": round(mm, 1),
        "dgemm_gflops": round(mm, 1),
        "read_gbs": round(bw, 2),
        "flop_limit_ms": round(limit * 1e3, 2),
        "ratio_to_flop_limit": round(t_mv / limit, 2),
        "one_query_bw_limit_ms": round(bw_limit * 1e3, 3),
        "one_query_ratio_to_bw_limit": round(best1 / bw_limit, 2),
        "speedup_vs_sklearn": round(t_sk / t_mv, 1),
        "one_query_ms": round(best1 * 1e3, 3),
        "25_queries_ms": round(best25 * 1e3, 3),
        "one_query_mean_only_ms": round(min(lat[(1, "mean1")], lat[(2, "mean1")]) * 1e3, 3),
        "max_abs_diff_vs_sklearn": float(f"{err:.2e}"),
    }
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
