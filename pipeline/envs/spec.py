"""Environment specs: what a simulator, a planner and an evaluation need to know of an environment.

An `EnvSpec` is built once from a dataset's `(env_id, env_kwargs)` (or the record of them in a
checkpoint) by `make_env_spec`. It owns the nominal MuJoCo model and the per-environment parts of
stepping: how an observation is read from and written into `MjData`, and one control step. The
batched simulator (`pipeline.envs.batch.BatchSim`) runs any spec; a new environment family (e.g.
OGBench point / ant mazes) is a new spec class, nothing else.

It also carries the facts that other modules would otherwise hard-code: the sizes of states and
actions, which state dimensions a goal refers to (`goal_dims`: x, y of the agent in the maze
plane), the control period and the maze layout.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import mujoco
import numpy as np

from pipeline.envs.maze import (
    SUPPORTED_ENVS,
    make_maze_env,
    max_episode_steps,
    maze_layout,
    point_env,
    step_point_mass,
)
from pipeline.errors import UserError


class EnvSpec(Protocol):
    """The interface `BatchSim`, deploy and validate use (see the module docstring).

    Attributes:
        env_id: The gymnasium id.
        state_dim: Size of an observation (the state the models see).
        action_dim: Size of an action.
        goal_dims: State dimensions a goal `[G]` refers to (and the agent's position in the plane).
        dt: Seconds per control step.
        max_episode_steps: Step limit of one evaluation episode.
        layout: The maze (`pipeline.envs.maze.maze_layout`): walls, free cells, bounds.
        model: The nominal MuJoCo model.
    """

    env_id: str
    state_dim: int
    action_dim: int
    goal_dims: tuple[int, ...]
    dt: float
    max_episode_steps: int
    layout: dict[str, Any]
    model: mujoco.MjModel

    def observe(self, data: mujoco.MjData) -> np.ndarray:
        """The observation `[state_dim]` (float64) of a simulator."""
        ...

    def set_observation(self, data: mujoco.MjData, observation: np.ndarray) -> None:
        """Write the state an observation `[state_dim]` describes into freshly reset `data`."""
        ...

    def control_step(self, model: mujoco.MjModel, data: mujoco.MjData, action: np.ndarray) -> None:
        """Advance one control step under `action [action_dim]`, as the gymnasium env does."""
        ...


@dataclass(frozen=True, eq=False)
class PointMazeSpec:
    """A gymnasium-robotics PointMaze: the point mass `[x, y, vx, vy]`, force actions `[fx, fy]`.

    Build it with `PointMazeSpec.create` (or `make_env_spec`).
    """

    env_id: str
    layout: dict[str, Any]
    model: mujoco.MjModel
    dt: float
    max_episode_steps: int
    state_dim: int = 4
    action_dim: int = 2
    goal_dims: tuple[int, ...] = (0, 1)

    @classmethod
    def create(cls, env_id: str, **env_kwargs: Any) -> PointMazeSpec:
        """The spec of `make_maze_env(env_id, **env_kwargs)` (e.g. `maze_map=` a custom map)."""
        env = make_maze_env(env_id, **env_kwargs)
        try:
            pe = point_env(env)
            return cls(env_id, maze_layout(env), pe.model, float(pe.dt), max_episode_steps(env_id))
        finally:
            env.close()

    def observe(self, data: mujoco.MjData) -> np.ndarray:
        """`[x, y, vx, vy]` = qpos, qvel."""
        return np.concatenate([data.qpos, data.qvel])

    def set_observation(self, data: mujoco.MjData, observation: np.ndarray) -> None:
        """qpos = `[x, y]`, qvel = `[vx, vy]` (what `PointEnv.reset` + `set_state` do)."""
        data.qpos[:] = observation[:2]
        data.qvel[:] = observation[2:4]

    def control_step(self, model: mujoco.MjModel, data: mujoco.MjData, action: np.ndarray) -> None:
        """`step_point_mass`: bit for bit gymnasium's `PointEnv.step`."""
        step_point_mass(model, data, action)


def make_env_spec(env_id: str, env_kwargs: dict[str, Any] | None = None) -> EnvSpec:
    """The spec of a dataset's environment (`DatasetInfo.env_id`, `.env_kwargs`).

    Raises:
        UserError: no simulator for `env_id` (e.g. data imported from a real robot).
    """
    if env_id not in SUPPORTED_ENVS:
        raise UserError(
            f"no simulator for environment {env_id!r}; this needs one of "
            f"{', '.join(SUPPORTED_ENVS)}"
        )
    return PointMazeSpec.create(env_id, **(env_kwargs or {}))
