"""GP training speed: what the one-thread, potri and subset choices buy on this machine.

Paper sizes: n = 900 points, d = 16 inputs (the blimp's 12-D state with yaw as cos/sin, plus
3 controls), m = 50 pseudo-inputs. Measured in one run:

1. One exact negative-log-marginal-likelihood evaluation (value and gradient) with the
   BLAS library's default threads vs one thread (training pins one thread).
2. ``K^-1`` from the Cholesky factor: LAPACK ``potri`` vs solving with the identity.
3. One sparse (FITC) evaluation, default threads vs one thread.
4. ``fit_exact`` on 2 outputs: hyperparameters on all points vs on a 300-point subset
   then polished on all (``hyper_points``), with the held-out RMS of both fits.
5. The README's run: ``gpbf collect --minutes 20`` then ``gpbf train`` with every default
   (five kinds, noise calibration), as separate processes: ``train_default_s`` (wall time of
   ``gpbf train``) and ``calibration_share`` (the calibration's part of the phases ``gpbf
   train`` reports). ``--quick``: a 5-minute flight; ``--smoke``: 30 s, tiny GP models.

One evaluation's flop floor: ``n^3`` (Cholesky ``n^3 / 3``, the inverse from it ``2 n^3 / 3``)
plus ``4 n^2 d`` (distances and the length-scale gradient) over one core's dgemm rate
(training pins one thread): ``exact_nll_ratio_to_flop_limit``.

The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.linalg as sla
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).parent))
from machine import best_time, dgemm_gflops, limits

from estimator_service.gp import exact_nll, fit_exact, sparse_nll
from estimator_service.gp.linalg import chol_inverse

N, D, M = 900, 16, 50


def data(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    x = rng.normal(size=(n, D))
    y = np.stack([np.sin(x[:, 0]) + 0.5 * x[:, 1] * x[:, 2], np.cos(x[:, 3]) * x[:, 4]], axis=1)
    return x, y + 0.05 * rng.normal(size=y.shape)


def gpbf(*args: str) -> str:
    """Run the ``gpbf`` command line in a new process; its stdout."""
    cmd = [sys.executable, "-c", "import sys; from agents.cli import main; sys.exit(main())", *args]
    return subprocess.run(cmd, check=True, capture_output=True, text=True, timeout=4 * 3600).stdout


def readme_run(minutes: float, smoke: bool) -> dict[str, float]:
    """``gpbf collect --minutes M`` then ``gpbf train`` with its defaults (``--smoke``: tiny
    models): the train command's wall seconds and the calibration's share of its phases."""
    with tempfile.TemporaryDirectory() as tmp:
        flight, models = Path(tmp) / "f1.npz", Path(tmp) / "models"
        gpbf("collect", "--minutes", str(minutes), "--quiet", "--out", str(flight))
        tiny = [
            "--points",
            "40",
            "--max-iter",
            "3",
            "--restarts",
            "1",
            "--calibration-seconds",
            "5",
            "--kinds",
            "gp",
        ]
        t0 = time.perf_counter()
        out = gpbf("train", str(flight), "--out", str(models), "--quiet", *(tiny if smoke else []))
        wall = time.perf_counter() - t0
    phases = json.loads(out.strip().splitlines()[-1])["train_seconds"]
    print(f"gpbf train on a {minutes}-minute flight: {wall:.1f} s, phases {phases}")
    share = phases["calibration"] / sum(phases.values())
    return {
        "train_default_s": round(wall, 1),
        "calibration_share": round(share, 3),
        "train_flight_minutes": minutes,
    }


def main() -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats and optimiser iterations")
    ap.add_argument("--smoke", action="store_true", help="--quick with a 30 s flight and tiny models")
    args = ap.parse_args()
    args.quick |= args.smoke
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
    with threadpool_limits(1):
        one_core = dgemm_gflops(3)
    floor = (N**3 + 4 * N * N * D) / (one_core * 1e9)
    readme = readme_run(0.5 if args.smoke else 5.0 if args.quick else 20.0, args.smoke)
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
        "exact_nll_ratio_to_flop_limit": round(t["exact_1thread"] / floor, 2),
        "dgemm_gflops_one_core": round(one_core, 1),
        **readme,
    }
    result.update(limits())  # this machine's dgemm rate and read bandwidth, for the ratios
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
