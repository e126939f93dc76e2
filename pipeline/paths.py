"""Where each stage reads and writes, relative to one data root (DVC tracks these paths)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Paths:
    """Artifact locations under `root` (default `data/`)."""

    root: Path = Path("data")

    def demos(self, name: str) -> Path:
        """The MCAP dataset `data/demos/<name>.mcap`."""
        return self.root / "demos" / f"{name}.mcap"

    def segments(self, name: str) -> Path:
        """The segments directory `data/segments/<name>/`."""
        return self.root / "segments" / name

    def model(self, name: str) -> Path:
        """The checkpoint directory `data/models/<name>/` (best model + `resume/` state)."""
        return self.root / "models" / name

    def live(self, stage: str) -> Path:
        """A stage's dvclive directory `data/reports/<stage>/` (metrics.json, plots/)."""
        return self.root / "reports" / stage

    def report(self, stage: str) -> Path:
        """A stage's metrics JSON `data/reports/<stage>.json`."""
        return self.root / "reports" / f"{stage}.json"
