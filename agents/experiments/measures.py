"""Table 7's improvement measures over fold means, shared by the reports and the gap sweep."""

from __future__ import annotations

import numpy as np

from estimator_service.tracking import GROUPS

__all__ = ["aggregate_gain", "improvement"]


def aggregate_gain(tr: dict, key: str, base: str) -> float:
    """Improvement (%) of ``key`` over ``base`` on the aggregate RMS (mean of the group RMS)."""
    return 100 * (1 - tr[key]["aggregate_rms"][0] / tr[base]["aggregate_rms"][0])


def improvement(tr: dict, key: str, base: str) -> float:
    """Table 7's aggregate improvement (%) of ``key`` over ``base``: each state group's RMS
    improvement, averaged over the four groups (from fold means)."""
    v, b = tr[key], tr[base]
    return float(100 * np.mean([1 - v[g][0] / b[g][0] for g in GROUPS]))
