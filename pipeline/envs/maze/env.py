"""PointMaze environments (gymnasium-robotics v3, the refactored D4RL maze2d) and their physics.

The state is the MuJoCo point mass `[x, y, vx, vy]`. One simulator step lasts `dt` = 0.01 s
(`frame_skip` 1). `step_point_mass` replays `PointEnv.step` without the gym wrappers: same action
clip, same velocity clip to [-5, 5] per axis, same MuJoCo calls, so it is bit-for-bit the
gymnasium dynamics (checked in tests/test_envs.py).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from pipeline.envs.ids import SUPPORTED_ENVS, Cell
from pipeline.envs.ids import layout_cell as layout_cell  # also imported from here
from pipeline.envs.physics import PHYSICS_SPEC, register_envs
from pipeline.errors import UserError

# `PointEnv.step` clips each velocity component to this before simulating (m/s).
MAX_AXIS_SPEED = 5.0
# Radius of the point mass' collision sphere in point.xml (m).
AGENT_RADIUS = 0.1


def check_env_id(env_id: str) -> None:
    """Raise `UserError` unless `env_id` is one of `SUPPORTED_ENVS`."""
    if env_id not in SUPPORTED_ENVS:
        raise UserError(
            f"unsupported maze env id {env_id!r}; use one of: {', '.join(SUPPORTED_ENVS)}"
        )


def max_episode_steps(env_id: str) -> int:
    """D4RL's step limit for one evaluation episode of `env_id` (300 / 600 / 800)."""
    check_env_id(env_id)
    return SUPPORTED_ENVS[env_id]


def _check_maze_map(maze_map: Any) -> list[list[int | str]]:
    """Validate a maze map (rows of 1 = wall, 0 / "r" / "g" / "c" = free); return a plain copy."""
    if not isinstance(maze_map, list | tuple) or not maze_map:
        raise UserError("maze_map must be a non-empty list of rows")
    rows = [list(row) for row in maze_map]
    width = len(rows[0])
    if width == 0 or any(len(row) != width for row in rows):
        raise UserError(f"maze_map rows must all have the same non-zero length, got {rows}")
    allowed = {0, 1, "r", "g", "c"}
    out: list[list[int | str]] = []
    for i, row in enumerate(rows):
        clean: list[int | str] = []
        for j, cell in enumerate(row):
            value = cell if isinstance(cell, str) else int(cell)
            if value not in allowed:
                raise UserError(f"maze_map[{i}][{j}] is {cell!r}; use 1, 0, 'r', 'g' or 'c'")
            clean.append(value)
        out.append(clean)
    if sum(cell != 1 for row in out for cell in row) < 2:
        raise UserError("maze_map needs at least two free cells")
    return out


def make_maze_env(env_id: str, maze_map: list[list[int | str]] | None = None, **kwargs: Any):
    """Make a PointMaze env with `gym.make`, optionally on a custom map.

    Args:
        env_id: One of `SUPPORTED_ENVS`.
        maze_map: Rows of cells (1 wall, 0 free; gymnasium's "r"/"g"/"c" also accepted); the
            env's own map if None. The outer ring should be walls.
        **kwargs: Passed on to `gym.make` (e.g. `max_episode_steps`, `render_mode`).

    Returns:
        The (wrapped) gymnasium env; `env.unwrapped` is a `PointMazeEnv`.
    """
    check_env_id(env_id)
    register_envs()
    if maze_map is not None:
        kwargs["maze_map"] = _check_maze_map(maze_map)
    env = gym.make(env_id, **kwargs)
    # gymnasium-robotics writes the maze's MJCF to /tmp and never deletes it; MuJoCo has loaded
    # the model by now, so remove it (otherwise every env leaks a file).
    Path(env.unwrapped.tmp_xml_file_path).unlink(missing_ok=True)
    return env


def point_env(env: gym.Env):
    """The MuJoCo `PointEnv` inside a (possibly wrapped) PointMaze env."""
    return env.unwrapped.point_env


def maze_of(env: gym.Env):
    """The gymnasium-robotics `Maze` (map, scaling, cell conversions) of a PointMaze env."""
    return env.unwrapped.maze


def free_cells(maze) -> list[Cell]:
    """All `(row, col)` cells of `maze` that are not walls, in row-major order."""
    return [
        (i, j) for i, row in enumerate(maze.maze_map) for j, cell in enumerate(row) if cell != 1
    ]


def cell_to_xy(maze, cell: Cell) -> np.ndarray:
    """Centre `[x, y]` (m) of cell `(row, col)`, using the maze's own conversion."""
    return np.asarray(maze.cell_rowcol_to_xy(np.asarray(cell)), dtype=np.float64)


def xy_to_cell(maze, xy: np.ndarray) -> Cell:
    """The `(row, col)` cell containing point `xy` (may lie outside the map or in a wall)."""
    i, j = maze.cell_xy_to_rowcol(np.asarray(xy, dtype=np.float64))
    return int(i), int(j)


def get_physics_state(env: gym.Env) -> np.ndarray:
    """The full MuJoCo physics state `[time, x, y, vx, vy]` (`mjSTATE_FULLPHYSICS`), a copy."""
    pe = point_env(env)
    state = np.empty(mujoco.mj_stateSize(pe.model, PHYSICS_SPEC))
    mujoco.mj_getState(pe.model, pe.data, state, PHYSICS_SPEC)
    return state


def set_physics_state(env: gym.Env, state: np.ndarray) -> None:
    """Restore a state from `get_physics_state` so that stepping continues the recorded run.

    The constraint solver's warm start (`qacc_warmstart`) is not part of `mjSTATE_FULLPHYSICS`;
    it is zeroed, as in a freshly reset env, so the result does not depend on the env's history.
    Stepping from the restored state reproduces the recorded next observation exactly when the
    ball touches no wall, and to round-off (measured: up to 2.2e-14) when it does: the solver
    stops at its tolerance from a different starting point.
    """
    pe = point_env(env)
    state = np.asarray(state, dtype=np.float64)
    size = mujoco.mj_stateSize(pe.model, PHYSICS_SPEC)
    if state.shape != (size,):
        raise UserError(f"physics state has shape {state.shape}, expected ({size},)")
    mujoco.mj_setState(pe.model, pe.data, state, PHYSICS_SPEC)
    pe.data.qacc_warmstart[:] = 0.0
    mujoco.mj_forward(pe.model, pe.data)


def step_point_mass(
    model: mujoco.MjModel, data: mujoco.MjData, action: tuple[float, float] | np.ndarray
) -> None:
    """Advance one control step exactly as gymnasium-robotics' `PointEnv.step` does.

    Same operations: clip the action to [-1, 1], clip each qvel component to +-`MAX_AXIS_SPEED`,
    set ctrl, `mj_step`, `mj_rnePostConstraint`. Faster (about 2x) because it skips the wrappers,
    the observation dict, numpy calls on 2-vectors and the `mj_forward` that `PointEnv.set_state`
    runs before stepping: `mj_step` recomputes everything that forward pass computes and MuJoCo's
    forward pass leaves the solver warm start alone, so the result is bit-for-bit the same
    (tests/test_envs.py replays generated data through `env.step` and compares exactly).
    """
    qvel = data.qvel
    vx, vy = qvel.tolist()
    if not (-MAX_AXIS_SPEED <= vx <= MAX_AXIS_SPEED and -MAX_AXIS_SPEED <= vy <= MAX_AXIS_SPEED):
        qvel[0] = min(max(vx, -MAX_AXIS_SPEED), MAX_AXIS_SPEED)
        qvel[1] = min(max(vy, -MAX_AXIS_SPEED), MAX_AXIS_SPEED)
    ax, ay = action
    data.ctrl[0] = min(max(float(ax), -1.0), 1.0)
    data.ctrl[1] = min(max(float(ay), -1.0), 1.0)
    mujoco.mj_step(model, data)
    mujoco.mj_rnePostConstraint(model, data)


def maze_layout(env: gym.Env) -> dict[str, Any]:
    """JSON-serializable description of the maze: enough to rebuild the env and draw its walls.

    Keys: `maze_map` (rows, 1 = wall), `maze_size_scaling` (cell side, m), `maze_height`,
    `x_map_center` / `y_map_center` (cell (0, 0)'s corner is at `(-x_map_center, y_map_center)`;
    x grows with the column, y decreases with the row), `n_rows`, `n_cols`, `free_cells` and
    `wall_cells` (`[row, col]`), `free_cell_centers` (`[x, y]`), `bounds` (`[xmin, xmax, ymin,
    ymax]` of the whole map) and `agent_radius`.
    """
    maze = maze_of(env)
    scale = float(maze.maze_size_scaling)
    maze_map = [[c if isinstance(c, str) else int(c) for c in row] for row in maze.maze_map]
    free = free_cells(maze)
    walls = [[i, j] for i, row in enumerate(maze_map) for j, c in enumerate(row) if c == 1]
    x_c, y_c = float(maze.x_map_center), float(maze.y_map_center)
    return {
        "maze_map": maze_map,
        "maze_size_scaling": scale,
        "maze_height": float(maze.maze_height),
        "x_map_center": x_c,
        "y_map_center": y_c,
        "n_rows": len(maze_map),
        "n_cols": len(maze_map[0]),
        "free_cells": [[i, j] for i, j in free],
        "wall_cells": walls,
        "free_cell_centers": [cell_to_xy(maze, c).tolist() for c in free],
        "bounds": [-x_c, -x_c + len(maze_map[0]) * scale, y_c - len(maze_map) * scale, y_c],
        "agent_radius": AGENT_RADIUS,
    }
