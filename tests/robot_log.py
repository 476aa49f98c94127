"""A small robot that is not the blimp, for the estimator-as-a-library tests: a unicycle
(position, heading, speed, turn rate) with a 1 Hz position fix and a compass."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

SYSTEM = {
    "name": "rover",
    "state": ["x", "y", "heading", "speed", "turn_rate"],
    "controls": ["accel", "turn_accel"],
    "sensors": [
        {"name": "gps", "outputs": ["x", "y"], "rate_hz": 1.0},
        {"name": "compass", "outputs": ["heading"], "periods": [2 * math.pi], "rate_hz": 10.0},
    ],
    "dt": 0.1,
    "state_periods": [0, 0, 2 * math.pi, 0, 0],
}


def simulate(rows: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """States ``(rows, 5)``, controls ``(rows, 2)`` and sensor values with NaN where none."""
    dt = SYSTEM["dt"]
    x = np.zeros((rows, 5))
    t = np.arange(rows) * dt
    u = np.stack([0.6 * np.sin(0.31 * t + rng.uniform(0, 6)), 0.8 * np.sin(0.53 * t + rng.uniform(0, 6))], 1)
    for k in range(rows - 1):
        px, py, h, v, w = x[k]
        x[k + 1] = [
            px + v * math.cos(h) * dt,
            py + v * math.sin(h) * dt,
            (h + w * dt + math.pi) % (2 * math.pi) - math.pi,
            v + (u[k, 0] - 0.5 * v) * dt + 0.01 * rng.standard_normal(),
            w + (u[k, 1] - 0.8 * w) * dt + 0.01 * rng.standard_normal(),
        ]
    gps = np.full((rows, 2), np.nan)
    fix = np.arange(rows) % 10 == 0
    gps[fix] = x[fix, :2] + 0.05 * rng.standard_normal((fix.sum(), 2))
    compass = (x[:, 2:3] + 0.02 * rng.standard_normal((rows, 1)) + math.pi) % (2 * math.pi) - math.pi
    return {"t": t, "x": x, "u": u, "gps": gps, "compass": compass}


def write_robot_log(folder: Path, rng: np.random.Generator, rows: int = 600) -> tuple[Path, Path]:
    """``folder/rover.csv`` and ``folder/rover.json`` (the system description)."""
    d = simulate(rows, rng)
    log, system = folder / "rover.csv", folder / "rover.json"
    system.write_text(json.dumps(SYSTEM))
    header = ["t", *SYSTEM["state"], *SYSTEM["controls"], "gps.x", "gps.y", "compass.heading"]
    with open(log, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for k in range(rows):
            vals = [d["t"][k], *d["x"][k], *d["u"][k], *d["gps"][k], *d["compass"][k]]
            w.writerow(["" if math.isnan(v) else f"{v:.6g}" for v in vals])
    return log, system
