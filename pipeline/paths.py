"""Where each stage reads and writes, relative to one data root (DVC tracks these paths).

The pipeline's own runs (`dvc repro`, or a stage command on the committed params) write under
`data/` and their headline metrics under `metrics/` (git-tracked, so experiments compare). An
ad-hoc run (`oposm deploy -S ...`) gets a `Paths` rooted in `data/runs/<run>/`: it writes only
there and reads each input from its own run folder when it made one, else from the pipeline's.
"""

from __future__ import annotations

from collections.abc import Iterable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path

from pipeline.io import Staging, check_outputs, staged_outputs


@dataclass(frozen=True)
class Paths:
    """Artifact locations under `root` (default `data/`).

    Attributes:
        root: Where this run writes its artifacts.
        metrics_root: Where its headline metrics go (`<metrics_root>/<stage>.json`); None:
            `metrics/` beside `root` (the repository's `metrics/` for the default `data/`).
        inputs: Another data root to read inputs from when `root` does not hold them (an ad-hoc
            run reads the pipeline's models and segments); None for the pipeline itself.
        model_dir: The skill model folder to read instead of `models/<name>/` (`--model`).
    """

    root: Path = Path("data")
    metrics_root: Path | None = None
    inputs: Path | None = None
    model_dir: Path | None = None

    @classmethod
    def for_run(cls, data: Path, run: str) -> Paths:
        """An ad-hoc run: writes under `data/runs/<run>/`, reads missing inputs from `data`."""
        root = data / "runs" / run
        return cls(root=root, metrics_root=root / "metrics", inputs=data)

    def existing(self, path: Path) -> Path:
        """`path` (under `root`) to read, or the same path under `inputs` where `root` lacks it."""
        if self.inputs is None or path.exists():
            return path
        try:
            relative = path.relative_to(self.root)
        except ValueError:
            return path
        fallback = self.inputs / relative
        return fallback if fallback.exists() else path

    def demos(self, name: str) -> Path:
        """The MCAP dataset `data/demos/<name>.mcap`."""
        return self.root / "demos" / f"{name}.mcap"

    def segments(self, name: str) -> Path:
        """The segments directory `data/segments/<name>/`."""
        return self.root / "segments" / name

    def model(self, name: str) -> Path:
        """The checkpoint directory `data/models/<name>/` (the best model), or `model_dir`."""
        return self.model_dir if self.model_dir is not None else self.root / "models" / name

    def dynamics(self, name: str) -> Path:
        """The single-step model `data/models/<name>-dynamics/` (beside the skill model)."""
        return self.root / "models" / f"{name}-dynamics"

    def policy(self, name: str, kind: str) -> Path:
        """A behaviour-cloning policy `data/models/<name>-<kind>/` (`kind`: bc | gcbc)."""
        return self.root / "models" / f"{name}-{kind}"

    def value(self, name: str) -> Path:
        """The goal-conditioned value `data/models/<name>-value/` (`oposm value`)."""
        return self.root / "models" / f"{name}-value"

    def scratch(self, stage: str, key: str) -> Path:
        """Resumable work of a stage, keyed by what it computes: `data/scratch/<stage>/<key>/`.

        Never a DVC output (DVC deletes outputs before a run, and persisted outputs disable its
        run cache); safe to delete when nothing runs.
        """
        return self.root / "scratch" / stage / key

    def recordings(self, stage: str) -> Path:
        """A stage's Rerun recordings `data/recordings/<stage>/`."""
        return self.root / "recordings" / stage

    def live(self, stage: str) -> Path:
        """A stage's detailed reports `data/reports/<stage>/` (dvclive files, CSVs, JSON)."""
        return self.root / "reports" / stage

    def timings(self, stage: str) -> Path:
        """A stage's wall-clock measurements `data/timings/<stage>.json`: beside its outputs,
        never one of them (they differ on every run; `stages.report.split_timings`)."""
        return self.root / "timings" / f"{stage}.json"

    def report(self, stage: str) -> Path:
        """A stage's detailed report `data/reports/<stage>/report.json`."""
        return self.live(stage) / "report.json"

    def metrics(self, stage: str) -> Path:
        """A stage's headline metrics `metrics/<stage>.json` (what `dvc exp show` compares)."""
        return self.metrics_dir / f"{stage}.json"

    @property
    def metrics_dir(self) -> Path:
        """Where the headline metrics go: `metrics_root`, or `metrics/` beside `root`."""
        return self.metrics_root if self.metrics_root is not None else self.root.parent / "metrics"

    def output_hint(self, path: Path) -> str:
        """Where else an output that cannot be written may go: the option that moves it."""
        if path.is_relative_to(self.metrics_dir):
            return "pass `--metrics` another folder"
        return "use `--data` elsewhere"

    def staged(
        self, files: Iterable[Path] = (), folders: Iterable[Path] = ()
    ) -> AbstractContextManager[Staging]:
        """`staged_outputs` of a stage's outputs (checked now, published together at the end),
        with this data root's way out in the messages."""
        return staged_outputs(files, folders, self.output_hint)

    def check(self, files: Iterable[Path] = (), folders: Iterable[Path] = ()) -> None:
        """`check_outputs` with this data root's way out: refuse a run whose outputs cannot be
        written, before its work."""
        check_outputs(files, folders, self.output_hint)
