"""Many PointMaze simulators stepped together, with per-environment failure detection.

All slots share the MuJoCo model of one gymnasium-robotics PointMaze env (the maze of the training
data) and each has its own `MjData`. A step is `step_point_mass`, bit-for-bit the gymnasium
`env.step` dynamics (tests/test_envs.py), without the wrappers' overhead. Stepping is a loop over
slots: one step costs microseconds, far below a planner call, so batching it in C would not change
the deploy wall time (measured in `oposm bench plan` / the deploy report).
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from pipeline.envs.maze import make_maze_env, maze_layout, point_env, step_point_mass

# MuJoCo warnings after which it has reset the simulation: the episode's state is no longer real.
_FATAL_WARNINGS = (
    mujoco.mjtWarning.mjWARN_BADQACC,
    mujoco.mjtWarning.mjWARN_BADQPOS,
    mujoco.mjtWarning.mjWARN_BADQVEL,
    mujoco.mjtWarning.mjWARN_BADCTRL,
)


class SimulationError(RuntimeError):
    """One slot's simulation failed (non-finite action or MuJoCo instability); others go on."""


class MazeBatch:
    """B point-mass simulators in one maze.

    Args:
        env_id: A supported PointMaze id.
        maze_map: The map (rows, 1 = wall) of the training data; the env's own if None.
        n: Number of slots.
    """

    def __init__(self, env_id: str, maze_map: list[list[int | str]] | None, n: int):
        self._env = make_maze_env(env_id, maze_map)
        self.layout: dict[str, Any] = maze_layout(self._env)
        pe = point_env(self._env)
        self.model = pe.model
        self.dt = float(pe.dt)
        self.datas = [mujoco.MjData(self.model) for _ in range(n)]

    def __len__(self) -> int:
        return len(self.datas)

    def reset(self, i: int, state: np.ndarray) -> None:
        """Put slot i at `state [x, y, vx, vy]`, as a fresh gymnasium reset would (zeroed warm
        start, time 0)."""
        data = self.datas[i]
        mujoco.mj_resetData(self.model, data)
        data.qpos[:] = state[:2]
        data.qvel[:] = state[2:4]
        mujoco.mj_forward(self.model, data)

    def state(self, i: int) -> np.ndarray:
        """Slot i's observation `[x, y, vx, vy]` (float64)."""
        data = self.datas[i]
        return np.concatenate([data.qpos, data.qvel])

    def step(self, i: int, action: np.ndarray) -> np.ndarray:
        """Apply `action [2]` to slot i for one control step; return the new state `[4]`.

        Raises:
            SimulationError: the action is not finite, or MuJoCo met an instability (after which
                it silently resets the state, which must not count as the agent's motion).
        """
        if not np.all(np.isfinite(action)):
            raise SimulationError(f"non-finite action {action.tolist()}")
        data = self.datas[i]
        step_point_mass(self.model, data, action)
        for w in _FATAL_WARNINGS:
            if data.warning[w].number:
                raise SimulationError(f"MuJoCo instability ({w.name}) at t = {data.time:.2f} s")
        return self.state(i)
