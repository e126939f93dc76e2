"""GCBC stage: goal-conditioned behaviour cloning p(a | s, g), OGBench's static-policy baseline.

Hindsight goals as OGBench's GCBC samples them (`pipeline.training.bc`); the goal is a position
(the environment's goal dims, x-y). Writes `data/models/<name>-gcbc/` and the report.
"""

from __future__ import annotations

from typing import Any

from pipeline.config import Params
from pipeline.paths import Paths
from stages.bc import fit_and_save


def run(params: Params, paths: Paths) -> dict[str, Any]:
    """Fit p(a | s, g) (`params.gcbc`)."""
    return fit_and_save(params, paths, "gcbc", params.gcbc)
