"""``gpbf gap-sweep``: where learned models start to pay (beyond the paper).

For each reality strength (0: the textbook world the parametric model describes, 1: the
lab, 2: twice as far), one scripted flight in the ``lab`` preset's drafts, k-fold
cross-validation as in ``gpbf reproduce``, and the Table 7 measure (per-group RMS
improvement over the same filter with the parametric model, averaged over the groups)
of the GP and EGP models with the EKF and the UKF. Writes ``gap_sweep.json``, a table
(``gap_sweep.md``) and a plot (``gap_sweep.png``).
"""

from __future__ import annotations

import time
from dataclasses import asdict, replace
from functools import partial
from pathlib import Path

from agents.experiments.gap_report import FILTERS, KINDS, describe
from agents.experiments.measures import improvement
from agents.experiments.parallel import check_jobs, run_all
from agents.experiments.reproduce import ReproduceSettings, split_folds, tracking
from agents.experiments.resume import fold_scores_path, kept, resume_check, trained
from agents.sim import collect_flight
from estimator_service.files import atomic_write_text, json_text
from estimator_service.flight import Flight
from estimator_service.progress import ProgressBar
from estimator_service.provenance import code_version, provenance
from estimator_service.tracking import mean_sd
from estimator_service.training import train_models

__all__ = ["STRENGTHS", "gap_sweep"]

STRENGTHS = (0.0, 0.5, 1.0, 2.0)


def _world(s: ReproduceSettings, strength: float) -> ReproduceSettings:
    """``s`` in the lab world at reality ``strength``."""
    return replace(s, reality="lab", reality_strength=strength)


def sweep_unit(out: Path, strength: float, i: int, train: Flight, test: Flight, s: ReproduceSettings) -> dict:
    """Fold ``i`` at ``strength``: its models (``out/models_s<strength>_fold<i>``, kept when
    complete) and their tracking scores ``{"<filter>/<kind>": scores}``, kept."""
    folder = out / f"models_s{strength:g}_fold{i}"
    if not trained(folder):
        train_models([train], folder, kinds=KINDS, settings=s.train_settings(), seed=s.seed + i)
    world = _world(s, strength)
    return kept(fold_scores_path(folder), lambda: {
        f"{f}/{k}": tracking(folder, test, world, f, k) for f in FILTERS for k in KINDS})  # fmt: skip


def gap_sweep(out: Path, s: ReproduceSettings, strengths: tuple[float, ...] = STRENGTHS,
              progress: bool = True, jobs: int = 1) -> dict:  # fmt: skip
    """Run the sweep into ``out`` (its folds in ``jobs`` worker processes); returns
    ``{strength: {"<filter>/<kind>": improvement %}}``.

    Resumes like :func:`~agents.experiments.reproduce.reproduce`: complete fold models and
    their scores from an earlier run with the same settings are kept."""
    check_jobs(jobs)
    start, code = time.monotonic(), code_version()  # the code that runs, not the checkout at the end
    resume_check(out, {**asdict(s), "strengths": list(strengths)})
    units = []
    for strength in strengths:
        flight = collect_flight(s.minutes * 60, seed=s.seed, env_kwargs=_world(s, strength).world)
        units += [partial(sweep_unit, out, strength, i, train, test, s)
                  for i, (train, test) in enumerate(split_folds(flight, s.folds))]  # fmt: skip
    with ProgressBar("gap sweep", len(units), unit="fold", enabled=progress) as bar:
        scores = run_all(units, jobs, lambda _: bar.advance())
    table: dict[str, dict[str, float]] = {}
    for j, strength in enumerate(strengths):
        track: dict[str, list] = {}
        for fold in scores[j * s.folds : (j + 1) * s.folds]:
            for key, v in fold.items():
                track.setdefault(key, []).append(v)
        tr = {k: mean_sd(v) for k, v in track.items()}
        table[f"{strength:g}"] = {
            f"{f}/{k}": improvement(tr, f"{f}/{k}", f"{f}/param")
            for f in FILTERS
            for k in KINDS
            if k != "param"
        }
    result = {"settings": asdict(s), "strengths": list(strengths), "improvement_pct": table,
              "provenance": provenance(time.monotonic() - start, code=code)}  # fmt: skip
    atomic_write_text(out / "gap_sweep.json", json_text(result, indent=2))
    atomic_write_text(out / "gap_sweep.md", "\n".join(describe(result)) + "\n")
    _plot(result, out / "gap_sweep.png")
    return result


def _plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5))
    x = [float(k) for k in result["improvement_pct"]]
    for col in next(iter(result["improvement_pct"].values())):
        ax.plot(x, [row[col] for row in result["improvement_pct"].values()], marker="o", label=col.upper())
    ax.axhline(0.0, color="grey", lw=0.8)
    ax.set_xlabel("reality strength (0 = textbook world)")
    ax.set_ylabel("improvement over Param (%)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
