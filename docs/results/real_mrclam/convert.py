"""Convert UTIAS MRCLAM robot logs into gpbf event logs and the robots' system description.

The dataset: K. Y. K. Leung, Y. Halpern, T. D. Barfoot, H. H. T. Liu, "The UTIAS
Multi-Robot Cooperative Localization and Mapping Dataset", International Journal of
Robotics Research 30(8), 969-974, 2011 (http://asrl.utias.utoronto.ca/datasets/mrclam/).
A public copy of Datasets 6 and 7 is in the GitHub repository ``joek5555/ROB530Project``,
folder ``UTIAS-dataset/MRCLAM_Dataset6``. Download ``Barcodes.dat``,
``Landmark_Groundtruth.dat`` and ``Robot<R>_{Groundtruth,Odometry,Measurement}.dat`` into
one folder, then::

    python docs/results/real_mrclam/convert.py RAW_FOLDER --robots 1 2

writes ``data/robot<R>.events.csv.gz`` (gpbf event logs: ``t, stream, values``) and
``mrclam.json`` (the description) beside this file. Raw files (whitespace separated,
``#`` comments): Groundtruth ``t x y heading`` (Vicon, ~64 Hz), Odometry ``t v w`` (the
commanded velocities, ~67 Hz), Measurement ``t barcode range bearing`` (the header says
subject, the values are barcodes: ``Barcodes.dat`` maps subject -> barcode),
Landmark_Groundtruth ``subject x y std_x std_y``. Readings of other robots (subjects 1-5)
are dropped; times are written relative to the robot's first command.
"""

from __future__ import annotations

import argparse
import gzip
import io
import json
import math
from pathlib import Path
from typing import BinaryIO

import numpy as np

from estimator_service.files import atomic_write, atomic_write_text

HERE = Path(__file__).resolve().parent
DT = 0.1
ROBOTS = range(1, 6)
FIRST_LANDMARK = 6  # subjects 1-5 are the robots
NOISE_FLOOR = [0.05, 0.01]  # range (m), bearing (rad): fixed before any result was seen
PROCESS_NOISE_FLOOR = [0.001, 0.001, 0.002]  # per step: 1 mm, 1 mm, 0.002 rad
CONTROL_DELAY = 0.2  # s: what experiment.py chooses on robot 1's training part (results.json)


def load(path: Path) -> np.ndarray:
    return np.atleast_2d(np.loadtxt(path, comments="#"))


def wrap(a):
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi


def landmarks(raw: Path) -> dict[int, tuple[float, float]]:
    return {int(s): (float(x), float(y)) for s, x, y, *_ in load(raw / "Landmark_Groundtruth.dat")}


def description(marks: dict[int, tuple[float, float]]) -> dict:
    """The robots' system description: a unicycle and one landmark sensor type whose
    constants are each landmark's surveyed position."""
    return {
        "name": "mrclam",
        "state": ["x", "y", "heading"],
        "state_periods": [0, 0, 2 * math.pi],
        "controls": ["v", "w"],
        "dt": DT,
        "groups": [
            {"name": "position_cm", "indices": [0, 1], "factor": 100.0},
            {"name": "heading_deg", "indices": [2], "factor": 180.0 / math.pi},
        ],
        "prediction_model": {
            "function": "mrclam_models:unicycle",
            "params": {"k_v": 1.0, "k_w": 1.0},
            "noise": "mrclam_models:unicycle_noise",
        },
        "sensor_types": [
            {
                "name": "landmark",
                "constants": ["lx", "ly"],
                "model": {
                    "function": "mrclam_models:range_bearing",
                    "params": {"range_bias": 0.0},
                    "jacobian": "mrclam_models:range_bearing_jacobian",
                },
            }
        ],
        "sensors": [
            {
                "name": f"lm{s}",
                "outputs": ["range", "bearing"],
                "periods": [0, 2 * math.pi],
                "type": "landmark",
                "constants": list(xy),
                "noise_floor": NOISE_FLOOR,
            }
            for s, xy in sorted(marks.items())
        ],
        "process_noise_floor": PROCESS_NOISE_FLOOR,
        "control_delay": CONTROL_DELAY,
    }


def event_lines(raw: Path, robot: int, marks: dict) -> tuple[str, dict]:
    """The robot's event log as CSV text and a summary."""
    gt = load(raw / f"Robot{robot}_Groundtruth.dat")
    od = load(raw / f"Robot{robot}_Odometry.dat")
    me = load(raw / f"Robot{robot}_Measurement.dat")
    subject = {int(b): int(s) for s, b in load(raw / "Barcodes.dat")[:, :2]}
    t0 = od[0, 0]
    out = io.StringIO()
    out.write("t,stream,v1,v2,v3\n")
    rows = [(t - t0, f"state,{x:.4f},{y:.4f},{wrap(h):.5f}") for t, x, y, h in gt]
    rows += [(t - t0, f"control,{v:.4f},{w:.4f}") for t, v, w in od]
    kept = 0
    for t, barcode, r, b in me:
        s = subject.get(int(barcode))
        if s is not None and s in marks:
            rows.append((t - t0, f"lm{s},{r:.4f},{wrap(b):.5f}"))
            kept += 1
    rows.sort(key=lambda row: row[0])
    for t, rest in rows:
        out.write(f"{t:.3f},{rest}\n")
    seconds = round(float(gt[-1, 0] - t0), 1)
    summary = {"robot": robot, "ground_truth": len(gt), "commands": len(od), "landmark_readings": kept,
               "other_readings_dropped": len(me) - kept, "seconds": seconds}  # fmt: skip
    return out.getvalue(), summary


def _gzip(raw: BinaryIO, text: str, name: str) -> None:
    """``text`` gzipped into ``raw`` under the file name ``name`` (not the temporary file's;
    mtime 0: the same data gives the same bytes)."""
    with gzip.GzipFile(name, mode="wb", compresslevel=9, fileobj=raw, mtime=0) as fh:
        fh.write(text.encode("utf-8"))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("raw", type=Path, help="folder of the raw MRCLAM .dat files")
    p.add_argument("--robots", type=int, nargs="+", default=[1, 2], choices=ROBOTS)
    p.add_argument("--out", type=Path, default=HERE)
    args = p.parse_args()
    marks = landmarks(args.raw)
    marks = {s: xy for s, xy in marks.items() if s >= FIRST_LANDMARK}
    (args.out / "data").mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "mrclam.json", json.dumps(description(marks), indent=1) + "\n")
    for robot in args.robots:
        text, summary = event_lines(args.raw, robot, marks)
        path = args.out / "data" / f"robot{robot}.events.csv.gz"
        atomic_write(path, lambda raw, text=text, name=path.name: _gzip(raw, text, name))
        print(json.dumps(summary))


if __name__ == "__main__":
    main()
