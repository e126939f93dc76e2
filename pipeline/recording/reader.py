"""Read an oposm MCAP dataset: its `DatasetInfo` from the summary, its episodes as a stream.

`iter_episodes` reads one chunk at a time through `mcap.reader` (log-time order, protobuf decoded
with the schema embedded in the file) and holds one episode at a time. Problems found while
streaming (dimensions that disagree with the metadata, non-finite values, episode or frame indices
out of order) are raised when reached, naming the episode and frame.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.dataset import DatasetInfo, Episode
from pipeline.errors import UserError
from pipeline.recording.files import DatasetFile, open_dataset


def read_info(path: str | Path) -> DatasetInfo:
    """The `DatasetInfo` of a dataset, from its metadata (reads the summary section only).

    Raises:
        UserError: The file is missing, not MCAP, truncated or corrupt, or not an oposm dataset.
    """
    with open_dataset(path) as dataset:
        return dataset.info


class _EpisodeBuilder:
    """Collects the decoded steps of one episode; checks and stacks them column by column."""

    def __init__(self, dataset: DatasetFile, index: int) -> None:
        self.dataset, self.index = dataset, index
        self.steps: list[Any] = []

    def add(self, step: Any) -> None:
        """Append one decoded `oposm.Step` message."""
        self.steps.append(step)

    def _fail(self, frame: int, problem: str) -> UserError:
        return self.dataset.invalid(f"episode {self.index}, frame {frame}: {problem}")

    def _vectors(self, name: str, dim: int) -> np.ndarray:
        """Repeated field `name` of all steps as `[N, dim]` float64 (checks lengths and values)."""
        rows = [getattr(step, name) for step in self.steps]
        lengths = np.fromiter(map(len, rows), np.int64, len(rows))
        bad = np.flatnonzero(lengths != dim)
        if bad.size:
            frame = int(bad[0])
            raise self._fail(
                frame, f"`{name}` has {lengths[frame]} values but the metadata says {dim}"
            )
        flat = np.fromiter(itertools.chain.from_iterable(rows), np.float64, len(rows) * dim)
        return self._finite(name, flat.reshape(len(rows), dim))

    def _finite(self, name: str, values: np.ndarray) -> np.ndarray:
        bad = np.argwhere(~np.isfinite(values))
        if bad.size:
            raise self._fail(int(bad[0][0]), f"`{name}` is {values[tuple(bad[0])]}")
        return values

    def _scalars(self, name: str, dtype: type) -> np.ndarray | None:
        """Optional scalar field `name` as `[N]`, None if no step has it (error if only some)."""
        n = len(self.steps)
        present = np.fromiter((step.HasField(name) for step in self.steps), bool, n)
        if not present.any():
            return None
        if not present.all():
            raise self._fail(int(np.argmin(present)), f"`{name}` is missing but set on other steps")
        values = np.fromiter((getattr(step, name) for step in self.steps), dtype, n)
        return self._finite(name, values) if dtype is np.float64 else values

    def finish(self) -> Episode:
        """The collected steps as an `Episode`, after checking them against the metadata."""
        n, info = len(self.steps), self.dataset.info
        expected = self.dataset.lengths[self.index]
        if n != expected:
            raise self.dataset.invalid(
                f"episode {self.index} has {n} steps but the metadata says {expected}"
            )
        frames = np.fromiter((step.frame_index for step in self.steps), np.int64, n)
        bad = np.flatnonzero(frames != np.arange(n))
        if bad.size:
            raise self._fail(int(bad[0]), f"message has frame_index {frames[bad[0]]}")
        time = np.fromiter((step.time for step in self.steps), np.float64, n)
        return Episode(
            index=self.index,
            observations=self._vectors("state", info.state_dim),
            actions=self._vectors("action", info.action_dim),
            time=self._finite("time", time),
            physics=self._vectors("physics", info.physics_dim) if info.physics_dim else None,
            goals=self._vectors("goal", info.goal_dim) if info.goal_dim else None,
            goal_reached=self._scalars("goal_reached", bool),
            rewards=self._scalars("reward", np.float64),
            terminals=self._scalars("terminal", bool),
        )


def iter_episodes(path: str | Path) -> Iterator[Episode]:
    """Stream the episodes of a dataset in file order, one `Episode` at a time.

    Yields:
        Episodes 0, 1, 2, ...: `observations` `[N, state_dim]`, `actions` `[N, action_dim]`,
        `time` `[N]` float64; `physics` `[N, physics_dim]` / `goals` `[N, goal_dim]` float64 or None
        when the dataset has none; `goal_reached` / `terminals` `[N]` bool and `rewards` `[N]`
        float64, each None when the episode's messages do not carry it.

    Raises:
        UserError: On opening (see `open_dataset`) or when a bad message is reached (names the
            episode and frame); episodes before it have already been yielded.
    """
    with open_dataset(path) as dataset:
        builder: _EpisodeBuilder | None = None
        for step in dataset.iter_steps():
            if builder is None or step.episode_index != builder.index:
                if builder is not None:
                    yield builder.finish()
                expected = 0 if builder is None else builder.index + 1
                if step.episode_index != expected or expected >= len(dataset.lengths):
                    raise dataset.invalid(
                        f"a message of episode {step.episode_index} follows "
                        f"{'the start' if builder is None else f'episode {builder.index}'} "
                        f"(episodes must be numbered 0 .. {len(dataset.lengths) - 1} in order)"
                    )
                builder = _EpisodeBuilder(dataset, expected)
            builder.add(step)
        if builder is None or builder.index != len(dataset.lengths) - 1:
            found = 0 if builder is None else builder.index + 1
            raise dataset.invalid(
                f"found {found} episodes but the metadata says {len(dataset.lengths)}"
            )
        yield builder.finish()


def read_episodes(path: str | Path) -> list[Episode]:
    """All episodes of a (small) dataset in memory; use `iter_episodes` for large ones."""
    return list(iter_episodes(path))
