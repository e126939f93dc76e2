"""Environment specs: what a simulator, a planner and an evaluation need to know of an environment.

An `EnvSpec` is built once from a dataset's `(env_id, env_kwargs)` (or the record of them in a
checkpoint) by `make_env_spec`. It owns the nominal MuJoCo model and the per-environment parts of
stepping: how an observation is read from and written into `MjData`, and one control step. The
batched simulator (`pipeline.envs.batch.BatchSim`) runs any spec; a new environment family (e.g.
OGBench point / ant mazes, `pipeline.envs.ogbench`; OGBench's manipulation,
`pipeline.envs.manipspace.env`; the Franka kitchen, `pipeline.envs.kitchen`) is a new spec class,
nothing else.

It also carries the facts that other modules would otherwise hard-code: the sizes of states,
actions and recorded physics states, which state dimensions a goal refers to (`goal_dims`: x, y
of the agent in the maze plane), the control period and the maze layout, and what a recorded
physics state is (`state_spec`, `set_physics_state`: `mjSTATE_FULLPHYSICS` for the mazes, more for
the manipulation envs, whose exact state also holds the solver's warm start). `check_physics_dim`
holds a dataset's physics states against it from the metadata alone, so ingest and segment refuse
a dataset recorded in another model before validate would.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

import mujoco
import numpy as np

from pipeline.dataset import DatasetInfo
from pipeline.envs.kitchen import KITCHEN_ENVS, is_kitchen, kitchen_spec
from pipeline.envs.manipspace.env import MANIPSPACE_ENVS, is_manipspace, manipspace_spec
from pipeline.envs.maze.env import (
    SUPPORTED_ENVS,
    make_maze_env,
    max_episode_steps,
    maze_layout,
    point_env,
    step_point_mass,
)
from pipeline.envs.ogbench import OGBENCH_MAZES, OGBenchMazeSpec, is_ogbench_maze
from pipeline.envs.physics import PHYSICS_SPEC, restore_physics
from pipeline.errors import UserError

# Every env id `make_env_spec` builds a simulator for.
SIMULATED_ENVS: tuple[str, ...] = (*SUPPORTED_ENVS, *OGBENCH_MAZES, *MANIPSPACE_ENVS, *KITCHEN_ENVS)


class EnvSpec(Protocol):
    """The interface `BatchSim`, deploy and validate use (see the module docstring).

    Attributes:
        env_id: The gymnasium id.
        state_dim: Size of an observation (the state the models see).
        action_dim: Size of an action.
        physics_dim: Size of a recorded physics state (`mj_stateSize` of `state_spec`), what
            datasets record per step so that validate and deploy can restore the simulator.
        state_spec: The `mjtState` components a physics state holds (`mjSTATE_FULLPHYSICS` for
            the mazes).
        goal_dims: State dimensions a goal `[G]` refers to (the mazes: the agent's position in
            the plane; manipulation: the objects' positions and states).
        dt: Seconds per control step.
        max_episode_steps: Step limit of one evaluation episode.
        layout: The maze (`pipeline.envs.maze.env.maze_layout`): walls, free cells, bounds.
        model: The nominal MuJoCo model.
    """

    env_id: str
    state_dim: int
    action_dim: int
    physics_dim: int
    state_spec: int
    goal_dims: tuple[int, ...]
    dt: float
    max_episode_steps: int
    layout: dict[str, Any]
    model: mujoco.MjModel

    def start_observation(self, xy: np.ndarray) -> np.ndarray:
        """The observation `[state_dim]` of an evaluation episode starting at rest at `xy [2]`."""
        ...

    def observe(self, data: mujoco.MjData) -> np.ndarray:
        """The observation `[state_dim]` (float64) of a simulator."""
        ...

    def set_observation(self, data: mujoco.MjData, observation: np.ndarray) -> None:
        """Write the state an observation `[state_dim]` describes into freshly reset `data`."""
        ...

    def set_physics_state(
        self, data: mujoco.MjData, state: np.ndarray, model: mujoco.MjModel | None = None
    ) -> None:
        """Put `data` (of `model`: the nominal one or a variant) in a recorded physics state
        `[physics_dim]`, as exactly as the state allows (module docstring)."""
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
    state_spec: ClassVar[int] = PHYSICS_SPEC

    @classmethod
    def create(cls, env_id: str, **env_kwargs: Any) -> PointMazeSpec:
        """The spec of `make_maze_env(env_id, **env_kwargs)` (e.g. `maze_map=` a custom map)."""
        env = make_maze_env(env_id, **env_kwargs)
        try:
            pe = point_env(env)
            return cls(env_id, maze_layout(env), pe.model, float(pe.dt), max_episode_steps(env_id))
        finally:
            env.close()

    @property
    def physics_dim(self) -> int:
        """`[time, x, y, vx, vy]`: 5."""
        return int(mujoco.mj_stateSize(self.model, PHYSICS_SPEC))

    def start_observation(self, xy: np.ndarray) -> np.ndarray:
        """`[x, y, 0, 0]`."""
        return np.concatenate([np.asarray(xy, dtype=np.float64)[:2], np.zeros(2)])

    def observe(self, data: mujoco.MjData) -> np.ndarray:
        """`[x, y, vx, vy]` = qpos, qvel."""
        return np.concatenate([data.qpos, data.qvel])

    def set_observation(self, data: mujoco.MjData, observation: np.ndarray) -> None:
        """qpos = `[x, y]`, qvel = `[vx, vy]` (what `PointEnv.reset` + `set_state` do)."""
        data.qpos[:] = observation[:2]
        data.qvel[:] = observation[2:4]

    def set_physics_state(
        self, data: mujoco.MjData, state: np.ndarray, model: mujoco.MjModel | None = None
    ) -> None:
        """`[time, x, y, vx, vy]`; the solver's warm start zeroed, as after a reset
        (`pipeline.envs.maze.env.set_physics_state`)."""
        restore_physics(model or self.model, data, state, PHYSICS_SPEC)

    def control_step(self, model: mujoco.MjModel, data: mujoco.MjData, action: np.ndarray) -> None:
        """`step_point_mass`: bit for bit gymnasium's `PointEnv.step`."""
        step_point_mass(model, data, action)


def make_env_spec(env_id: str, env_kwargs: dict[str, Any] | None = None) -> EnvSpec:
    """The spec of a dataset's environment (`DatasetInfo.env_id`, `.env_kwargs`).

    gymnasium-robotics PointMazes (`PointMazeSpec`, `env_kwargs` may hold a custom `maze_map`),
    OGBench's point and ant mazes (`pipeline.envs.ogbench`, no kwargs: their mazes are fixed),
    OGBench's manipulation envs (`pipeline.envs.manipspace`: cube-single, cube-double, scene) and
    gymnasium-robotics' Franka kitchen (`pipeline.envs.kitchen`: `env_kwargs` name its subtasks).

    Raises:
        UserError: no simulator for `env_id` (e.g. data imported from a real robot).
    """
    if is_manipspace(env_id):
        return manipspace_spec(env_id)
    if is_kitchen(env_id):
        return kitchen_spec(env_kwargs)
    if is_ogbench_maze(env_id) or env_id.endswith("maze-teleport-v0"):
        return OGBenchMazeSpec.create(env_id)  # teleport: the error says why not
    if env_id not in SUPPORTED_ENVS:
        raise UserError(
            f"no simulator for environment {env_id!r}; this needs one of "
            f"{', '.join(SIMULATED_ENVS)}"
        )
    return PointMazeSpec.create(env_id, **(env_kwargs or {}))


def check_physics_dim(info: DatasetInfo, where: str, fix: str) -> None:
    """Check that the physics states `info` describes fit its environment's MuJoCo state.

    Nothing to check for a dataset without physics states or without a simulator here.

    Args:
        info: The dataset's metadata (`physics_dim`, `env_id`, `env_kwargs`).
        where: The file the user knows the dataset by, first in the message.
        fix: What to do about it, last in the message.

    Raises:
        UserError: `info.physics_dim` differs from the environment's `EnvSpec.physics_dim`.
    """
    if not info.physics_dim or info.env_id not in SIMULATED_ENVS:
        return
    expected = make_env_spec(info.env_id, info.env_kwargs).physics_dim
    if info.physics_dim != expected:
        raise UserError(
            f"{where}: its physics states have {info.physics_dim} numbers per step, but the "
            f"MuJoCo state of {info.env_id} has {expected}; {fix}"
        )
