"""The results stage's shared helpers, from the one report module (`pipeline.reporting.common`:
reading reports, the format of rates and intervals, the verdict rules, the stamp)."""

from __future__ import annotations

from pipeline.reporting.common import (
    Report,
    cell,
    code_version,
    pct,
    rate,
    read,
    separated,
    versus,
)

__all__ = ["Report", "cell", "code_version", "pct", "rate", "read", "separated", "versus"]
