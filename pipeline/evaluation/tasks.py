"""Evaluation tasks in the maze of the training data: where each episode starts and its goal.

- `corners`: the D4RL maze2d task the paper evaluates (§4.2): from one corner of the maze to the
  opposite one. Start in the free cell nearest the top-left corner (smallest row + column), goal at
  the centre of the free cell nearest the bottom-right one (largest row + column); medium: (1, 1)
  to (6, 6), as D4RL's maze2d-medium goal.
- `random_goal`: the paper's random-goal variant (§4.4, table 4): the goal is drawn uniformly from
  the locations present in the training data, the start is a random free cell other than the
  goal's cell.
- `goal`: a user-given goal (`deploy.goal`), from random free cells other than its own.

Starts are cell centres plus uniform noise of +- `start_noise` per axis (D4RL's reset noise: 0.1),
at rest. Every episode has its own seed, derived from (seed, task, episode), so an episode is the
same whichever others run beside it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.envs.maze import layout_cell
from pipeline.errors import UserError
from pipeline.segments import Segments

TASKS = ("corners", "random_goal", "goal")


@dataclass(frozen=True)
class EpisodeSpec:
    """One evaluation episode.

    Attributes:
        task: Task name (one of `TASKS`).
        index: Episode number within the task.
        start: `[4]` initial state `[x, y, vx, vy]`.
        goal: `[2]` goal position `[x, y]`.
        seed: Seed of the episode's planner and action noise.
    """

    task: str
    index: int
    start: np.ndarray
    goal: np.ndarray
    seed: int


def check_task(name: str) -> None:
    """Raise `UserError` unless `name` is one of `TASKS`."""
    if name not in TASKS:
        raise UserError(f"unknown task {name!r}; use one of: {', '.join(TASKS)}")


def check_goal(layout: dict[str, Any], goal: np.ndarray) -> tuple[int, int]:
    """The free cell holding `goal [x, y]`.

    Raises:
        UserError: the goal is outside the maze or inside a wall.
    """
    goal = np.asarray(goal, dtype=np.float64)
    if goal.shape != (2,) or not np.all(np.isfinite(goal)):
        raise UserError(f"a goal is a finite [x, y] pair, got {goal.tolist()}")
    xmin, xmax, ymin, ymax = layout["bounds"]
    if not (xmin < goal[0] < xmax and ymin < goal[1] < ymax):
        raise UserError(
            f"goal {goal.tolist()} is outside the maze (x in ({xmin:g}, {xmax:g}), "
            f"y in ({ymin:g}, {ymax:g}))"
        )
    row, col = layout_cell(layout, float(goal[0]), float(goal[1]))
    if layout["maze_map"][row][col] == 1:
        raise UserError(f"goal {goal.tolist()} is inside a wall (cell row {row}, column {col})")
    return row, col


def train_locations(segments: Segments, dims: tuple[int, ...]) -> np.ndarray:
    """`[N, G]` positions (state dims `dims`: the environment spec's `goal_dims`) of every step of
    the train split's episodes (the goals' pool)."""
    offsets, mask = segments.episode_offsets, segments.episode_split == 0
    steps = np.concatenate(
        [np.arange(offsets[e], offsets[e + 1]) for e in np.flatnonzero(mask)]
        or [np.zeros(0, np.int64)]
    )
    return segments.states[steps][:, list(dims)].astype(np.float64)


class MazeTasks:
    """Draws `EpisodeSpec`s for the tasks of one maze.

    Args:
        layout: `maze_layout` of the maze.
        locations: `[N, 2]` training-data positions (goals of `random_goal`).
        start_noise: Uniform noise (+-, m) on start positions.
        goal: The `goal` task's `[x, y]`, or None.
        seed: Base seed of every episode.
    """

    def __init__(
        self,
        layout: dict[str, Any],
        locations: np.ndarray,
        start_noise: float = 0.1,
        goal: np.ndarray | None = None,
        seed: int = 0,
    ):
        self.layout = layout
        self.locations = locations
        self.start_noise = start_noise
        self.goal = None if goal is None else np.asarray(goal, dtype=np.float64)
        self.seed = seed
        self.cells = [tuple(c) for c in layout["free_cells"]]
        self.centers = np.asarray(layout["free_cell_centers"], dtype=np.float64)
        if self.goal is not None:
            check_goal(layout, self.goal)

    def episodes(self, task: str, n: int) -> list[EpisodeSpec]:
        """The first `n` episodes of `task` (the same ones for any `n` that includes them)."""
        check_task(task)
        if task == "random_goal" and len(self.locations) == 0:
            raise UserError("random_goal needs training-data locations, and there are none")
        if task == "goal" and self.goal is None:
            raise UserError("the goal task needs deploy.goal: [x, y]")
        return [self._episode(task, k) for k in range(n)]

    def _episode(self, task: str, k: int) -> EpisodeSpec:
        seq = np.random.SeedSequence([self.seed, TASKS.index(task), k])
        rng = np.random.default_rng(seq)
        if task == "corners":
            order = np.argsort([r + c for r, c in self.cells], kind="stable")
            start_cell, goal_cell = int(order[0]), int(order[-1])
            goal = self.centers[goal_cell]
        else:
            goal = (
                self.goal if task == "goal" else self.locations[rng.integers(len(self.locations))]
            )
            goal_rc = layout_cell(self.layout, float(goal[0]), float(goal[1]))
            choices = [i for i, c in enumerate(self.cells) if c != goal_rc]
            start_cell = choices[rng.integers(len(choices))]
        xy = self.centers[start_cell] + rng.uniform(-self.start_noise, self.start_noise, 2)
        return EpisodeSpec(
            task=task,
            index=k,
            start=np.concatenate([xy, np.zeros(2)]),
            goal=np.asarray(goal, dtype=np.float64).copy(),
            seed=int(seq.generate_state(1)[0]),
        )
