"""Evaluation tasks in the maze of the training data: where each episode starts and its goal.

- `corners`: the D4RL maze2d task the paper evaluates (§4.2): from one corner of the maze to the
  opposite one. Start in the free cell nearest the top-left corner (smallest row + column), goal at
  the centre of the free cell nearest the bottom-right one (largest row + column); medium: (1, 1)
  to (6, 6), as D4RL's maze2d-medium goal.
- `random_goal`: the paper's random-goal variant (§4.4, table 4): the goal is drawn uniformly from
  the locations present in the training data, the start is a random free cell other than the
  goal's cell.
- `goal`: a user-given goal (`deploy.goal`), from random free cells other than its own.
- `ogbench`: an OGBench maze's five evaluation tasks exactly as OGBench defines them (its
  `task_infos`: start and goal cells; both get uniform noise of +- 1 per axis, OGBench's
  `add_noise`); they are reported as five tasks, `ogbench-task1` .. `ogbench-task5`
  (`MazeTasks.expand`). In OGBench mazes (`pipeline.envs.ogbench`), and in OGBench's
  manipulation envs (`manipulation_episodes`): each episode starts in the exact physics state
  OGBench's evaluation reset leaves (`ManipSpaceSpec.task_start`, seeded per episode), its goal
  is the task's object configuration at the spec's `goal_dims` (`goal_vector`; in a puzzle the
  goal button states of OGBench's `set_tasks`, from its init button states). The maze tasks
  (corners, random_goal, goal) are refused there.
- `kitchen`: the Franka kitchen's D4RL task set (`kitchen_episodes`): its four subtasks from the
  env's reset state, exactly (`KitchenSpec.task_start`); reported under the task set's name
  (`kitchen-mixed`, ...). Success and score are D4RL's (`pipeline.evaluation.goals`).

Other starts are cell centres plus uniform noise of +- `start_noise` per axis (D4RL's reset
noise: 0.1). Every start is at rest (`EnvSpec.start_observation`). Every episode has its own
seed, derived from (seed, task, episode), so an episode is the same whichever others run beside it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.envs.ids import OGBENCH_PREFIX, TASKS, layout_cell
from pipeline.envs.kitchen import CUSTOM_TASK, KITCHEN_TASK_SETS, KitchenSpec
from pipeline.envs.manipspace.env import ManipSpaceSpec
from pipeline.envs.ogbench import TASK_NOISE, is_ogbench_maze, ogbench_tasks
from pipeline.errors import UserError
from pipeline.segments import Segments


@dataclass(frozen=True)
class EpisodeSpec:
    """One evaluation episode.

    Attributes:
        task: Task name (one of `TASKS`; `ogbench-taskK` for OGBench's task K).
        index: Episode number within the task.
        start: `[state_dim]` initial state (`[x, y, vx, vy]` in a PointMaze, `[x, y]` for
            OGBench's point).
        goal: `[G]` the goal at the spec's `goal_dims` (`[x, y]` in a maze).
        seed: Seed of the episode's planner and action noise.
        physics: `[physics_dim]` the exact start state to restore (OGBench's manipulation
            tasks), or None: start at rest in `start` (`EnvSpec.set_observation`).
    """

    task: str
    index: int
    start: np.ndarray
    goal: np.ndarray
    seed: int
    physics: np.ndarray | None = None


def check_task(name: str) -> None:
    """Raise `UserError` unless `name` is one of `TASKS`."""
    if name not in TASKS:
        raise UserError(f"unknown task {name!r}; use one of: {', '.join(TASKS)}")


def check_goal(
    layout: dict[str, Any], goal: np.ndarray, key: str = "deploy.goal"
) -> tuple[int, int]:
    """The free cell holding `goal [x, y]` (the param `key`, for messages).

    Raises:
        UserError: the goal is outside the maze or inside a wall; the message names `key` and
            the center of the nearest free cell to set instead.
    """
    goal = np.asarray(goal, dtype=np.float64)
    if goal.shape != (2,) or not np.all(np.isfinite(goal)):
        raise UserError(f"{key}: a goal is a finite [x, y] pair, got {goal.tolist()}")
    xmin, xmax, ymin, ymax = layout["bounds"]
    if not (xmin < goal[0] < xmax and ymin < goal[1] < ymax):
        raise UserError(
            f"{key} {goal.tolist()} is outside the maze (x in ({xmin:g}, {xmax:g}), "
            f"y in ({ymin:g}, {ymax:g})); {_nearest_free(layout, goal, key)}"
        )
    row, col = layout_cell(layout, float(goal[0]), float(goal[1]))
    if layout["maze_map"][row][col] == 1:
        raise UserError(
            f"{key} {goal.tolist()} is inside a wall (cell row {row}, column {col}); "
            f"{_nearest_free(layout, goal, key)}"
        )
    return row, col


def _nearest_free(layout: dict[str, Any], goal: np.ndarray, key: str) -> str:
    """'the nearest free cell is ...: set key=[x, y]' for a goal that is not in a free cell."""
    centers = np.asarray(layout["free_cell_centers"], dtype=np.float64)
    nearest = centers[np.argmin(np.linalg.norm(centers - goal, axis=1))]
    x, y = (round(float(v), 4) for v in nearest)
    row, col = layout_cell(layout, x, y)
    return (
        f"the nearest free cell (row {row}, column {col}) is centered at [{x:g}, {y:g}]: set "
        f"{key}=[{x:g},{y:g}]"
    )


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
        start_state: `[x, y]` -> the initial state there at rest (`EnvSpec.start_observation`);
            default `[x, y, 0, 0]` (PointMaze).
        env_id: The environment, for its own tasks (`ogbench`: an OGBench maze's id).
    """

    def __init__(
        self,
        layout: dict[str, Any],
        locations: np.ndarray,
        start_noise: float = 0.1,
        goal: np.ndarray | None = None,
        seed: int = 0,
        start_state: Callable[[np.ndarray], np.ndarray] | None = None,
        env_id: str = "",
    ):
        self.layout = layout
        self.start_state = start_state or (lambda xy: np.concatenate([xy, np.zeros(2)]))
        self.env_id = env_id
        self.locations = locations
        self.start_noise = start_noise
        self.goal = None if goal is None else np.asarray(goal, dtype=np.float64)
        self.seed = seed
        self.cells = [tuple(c) for c in layout["free_cells"]]
        self.centers = np.asarray(layout["free_cell_centers"], dtype=np.float64)
        if self.goal is not None:
            check_goal(layout, self.goal)

    def expand(self, tasks: list[str], n: int) -> dict[str, list[EpisodeSpec]]:
        """`n` episodes of each task by reported task name: `ogbench` becomes its five tasks."""
        out: dict[str, list[EpisodeSpec]] = {}
        for task in tasks:
            if task == "ogbench":
                out.update(self.ogbench_episodes(n))
            else:
                out[task] = self.episodes(task, n)
        return out

    def ogbench_episodes(self, n: int) -> dict[str, list[EpisodeSpec]]:
        """`n` episodes of each of the OGBench maze's five tasks, `{"ogbench-task1": [...]}`."""
        if not is_ogbench_maze(self.env_id):
            raise UserError(
                f"the ogbench task needs an OGBench maze (pointmaze-medium-v0, ...), but the data "
                f"is in {self.env_id or 'no simulated environment'}; use corners or random_goal"
            )
        out = {}
        for number, info in enumerate(ogbench_tasks(self.env_id), start=1):
            name = OGBENCH_PREFIX + info["name"]
            out[name] = [self._ogbench_episode(name, number, info, k) for k in range(n)]
        return out

    def _ogbench_episode(self, name: str, number: int, info: dict, k: int) -> EpisodeSpec:
        seq = np.random.SeedSequence([self.seed, TASKS.index("ogbench"), number, k])
        rng = np.random.default_rng(seq)
        start = info["init_xy"] + rng.uniform(-TASK_NOISE, TASK_NOISE, 2)
        goal = info["goal_xy"] + rng.uniform(-TASK_NOISE, TASK_NOISE, 2)
        return EpisodeSpec(
            task=name,
            index=k,
            start=self.start_state(start),
            goal=goal,
            seed=int(seq.generate_state(1)[0]),
        )

    def episodes(self, task: str, n: int) -> list[EpisodeSpec]:
        """The first `n` episodes of `task` (the same ones for any `n` that includes them)."""
        check_task(task)
        if task == "kitchen":
            raise UserError(
                f"the kitchen task needs data in the Franka kitchen, but the data is in "
                f"{self.env_id or 'a maze'}; use corners or random_goal"
            )
        if task == "ogbench":
            return [s for specs in self.ogbench_episodes(n).values() for s in specs]
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
            start=self.start_state(xy),
            goal=np.asarray(goal, dtype=np.float64).copy(),
            seed=int(seq.generate_state(1)[0]),
        )


MAZE_TASKS = ("corners", "random_goal", "goal")


def check_manipulation_tasks(env_id: str, tasks: list[str]) -> None:
    """A one-line `UserError` for a maze task (corners, random_goal, goal) or the kitchen task in
    a manipulation env."""
    maze_only = [t for t in tasks if t != "ogbench"]
    if maze_only:
        what = (
            "maze tasks (start cells, goal positions in a plane)"
            if "kitchen" not in maze_only
            else "not OGBench's tasks (the maze tasks need a maze, kitchen the Franka kitchen)"
        )
        raise UserError(
            f"deploy.tasks {maze_only}: {what}; "
            f"{env_id} has OGBench's five object-goal tasks: set deploy.tasks=[ogbench]"
        )


def manipulation_episodes(
    spec: ManipSpaceSpec, tasks: list[str], n: int, seed: int
) -> dict[str, list[EpisodeSpec]]:
    """`n` episodes of each of OGBench's five evaluation tasks of a manipulation env,
    `{"ogbench-task1": [...], ...}`: episode k of task K starts from `spec.task_start(K, s)`, its
    reset seed `s` and the episode's own seed drawn from (seed, "ogbench", K, k).

    The start is OGBench's reset state exactly but for the solver's warm start, which OGBench's
    reset leaves from two unseeded random actions: it is zeroed (`ManipSpaceSpec.cold`), so an
    episode is a function of its seed (the first step then differs from OGBench's in the last
    bits of the solver, nothing a success rate could see).

    Raises:
        UserError: a task other than `ogbench` (the maze tasks need a maze).
    """
    check_manipulation_tasks(spec.env_id, tasks)
    out: dict[str, list[EpisodeSpec]] = {}
    for task in spec.tasks():
        name = f"{OGBENCH_PREFIX}task{task.task_id}"
        episodes = []
        for k in range(n):
            seq = np.random.SeedSequence([seed, TASKS.index("ogbench"), task.task_id, k])
            episode_seed, reset_seed = (int(v) for v in seq.generate_state(2))
            start = spec.task_start(task.task_id, reset_seed)
            episodes.append(
                EpisodeSpec(
                    task=name,
                    index=k,
                    start=start.observation,
                    goal=spec.goal_vector(start.goal),
                    seed=episode_seed,
                    physics=spec.cold(start.physics),
                )
            )
        out[name] = episodes
    return out


def check_kitchen_tasks(env_id: str, tasks: list[str]) -> None:
    """A one-line `UserError` for any task but `kitchen` in the Franka kitchen."""
    other = [t for t in tasks if t != "kitchen"]
    if other:
        raise UserError(
            f"deploy.tasks {other}: not tasks of {env_id}, which is evaluated on its D4RL task "
            "set: set deploy.tasks=[kitchen]"
        )


def kitchen_episodes(
    spec: KitchenSpec, tasks: list[str], n: int, seed: int, task_set: str | None = None
) -> dict[str, list[EpisodeSpec]]:
    """`n` episodes of the kitchen's D4RL task set, `{task_set: [...]}`: each starts from the
    env's reset state exactly (`KitchenSpec.task_start`; the reset is deterministic, the seed
    drawn from (seed, "kitchen", k) is the episode's own: planner and action noise), its goal is
    the set's subtasks' goals at the spec's `goal_dims`.

    Args:
        task_set: The name to report (the dataset's, `generator["kitchen_task_set"]`); default
            the spec's first task set (kitchen-partial and kitchen-complete share subtasks).

    Raises:
        UserError: a task other than `kitchen`, or subtasks that are no D4RL task set.
    """
    check_kitchen_tasks(spec.env_id, tasks)
    names = [t.name for t in spec.tasks() if t.name != CUSTOM_TASK]
    if not names:
        known = ", ".join(KITCHEN_TASK_SETS)
        raise UserError(
            f"the kitchen's subtasks {list(spec.subtasks)} are no known task set ({known}); "
            "deploy evaluates a D4RL task set: train on a dataset of one of them"
        )
    name = task_set if task_set in names else names[0]
    out = []
    for k in range(n):
        seq = np.random.SeedSequence([seed, TASKS.index("kitchen"), k])
        episode_seed, reset_seed = (int(v) for v in seq.generate_state(2))
        start = spec.task_start(name, reset_seed)
        out.append(
            EpisodeSpec(
                task=name,
                index=k,
                start=start.observation,
                goal=spec.goal_vector(start.goal),
                seed=episode_seed,
                physics=spec.cold(start.physics),
            )
        )
    return {name: out}
