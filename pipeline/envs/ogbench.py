"""OGBench's locomotion mazes (`ogbench.locomaze`): the point's physics, the maze layout, its tasks.

What OGBench's point really is (read from `ogbench/locomaze/point.py`, `maze.py`, `point.xml` of
the installed ogbench 1.2.2, and checked step for step in tests/test_ogbench.py):

- **Observation** `[x, y]`: `qpos` of two slide joints, nothing else (no velocity).
- **Action** `[dx, dy]`: a displacement command. `PointEnv.step` sets `qpos += 0.2 * action`,
  zeroes `qvel` and runs `mj_step` 5 times (timestep 0.02 s, RK4: 0.1 s a control step). The
  motors are never driven (`ctrl` stays 0), so away from walls the point moves by exactly
  `0.2 * action`; a displacement into a wall is undone by the wall contact during the 5 substeps
  (the point is a sphere of radius 0.7 in cells of 4 x 4). The env itself does not clip actions;
  OGBench's evaluation (`impls/utils/evaluation.py`) and data generation clip them to [-1, 1],
  and so does `control_step` here (a no-op for actions in range, so the step stays bit for bit).
  The state is Markov in `[x, y]`: the velocity left by a contact is zeroed by the next step.
- **Maze**: cell `(i, j)` of OGBench's `maze_map` has its centre at `x = 4 j - 4`, `y = 4 i - 4`,
  so y grows with the row, against the gymnasium-robotics convention of `maze_layout` (y falls with
  the row). `ogbench_layout` therefore lists the rows bottom-up (layout row `r` = OGBench row
  `n_rows - 1 - r`) so that every consumer of a layout (tasks, checks, Rerun views) works
  unchanged and draws the maze as OGBench renders it; `ogbench_cell` converts back.
- **Tasks and success**: 5 fixed `(init_ij, goal_ij)` pairs per maze (`task_infos`); start and
  goal get uniform noise of +-1 per axis (`add_noise`: `noise * maze_unit / 4`); success is being
  within 1.0 of the goal (0.5 for the ant); an episode lasts at most 1000 steps.

The ant mazes share the maze, tasks and success rule; their state is `qpos + qvel` (29) and a
step is `MujocoEnv.do_simulation` (ctrl = action, 5 substeps): `OGBenchAntMazeSpec`.
The teleport mazes (`*maze-teleport-v0`) add one random event: after a step that ends within
1.5 of an inbound teleport's centre, OGBench moves the agent (`set_xy`) to one of the outbound
teleports, drawn uniformly with numpy's global generator. The observation that step returns is the
one before the move; the next step starts from the outbound teleport. Here the move is applied at
the start of the next step instead (`OGBenchMazeSpec.teleport`, drawing from the slot's own
generator; `BatchSim` remembers which slots' last step ended at a teleport, as a reset there moves
nothing): the same observations, and a recorded state always holds its observation.
"""

from __future__ import annotations

import functools
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import gymnasium
import mujoco
import numpy as np

from pipeline.envs.ids import OGBENCH_MAZES
from pipeline.envs.physics import PHYSICS_SPEC, restore_physics
from pipeline.errors import UserError

# Step limit of an evaluation episode (the registered `max_episode_steps` of these ids).
EPISODE_STEPS = 1000
# OGBench's maze geometry (`MazeEnv`: maze_unit 4, offsets 4, noise 1).
MAZE_UNIT = 4.0
MAZE_OFFSET = 4.0
TASK_NOISE = 1.0 * MAZE_UNIT / 4  # +- per axis on task starts and goals
# Success distance to the goal (`MazeEnv._goal_tol`).
GOAL_TOLERANCE = {"point": 1.0, "ant": 0.5}
# Radius of each locomotor's body in the maze plane (point.xml's sphere; the ant's torso).
AGENT_RADIUS = {"point": 0.7, "ant": 0.25}
# The point's displacement per unit of action (`PointEnv.step`: `action = 0.2 * action`).
POINT_STEP = 0.2


def is_ogbench_maze(env_id: str) -> bool:
    """Whether `env_id` is an OGBench maze this module simulates."""
    return env_id in OGBENCH_MAZES


def check_ogbench_id(env_id: str) -> tuple[str, str]:
    """`(locomotion, maze type)` of a supported id; a one-line `UserError` for any other."""
    if env_id not in OGBENCH_MAZES:
        raise UserError(
            f"unsupported OGBench env id {env_id!r}; use one of: {', '.join(OGBENCH_MAZES)}"
        )
    return OGBENCH_MAZES[env_id]


def make_ogbench_env(env_id: str, **kwargs: Any) -> gymnasium.Env:
    """`gymnasium.make(env_id, **kwargs)` of a supported OGBench maze (e.g. `terminate_at_goal`).

    OGBench writes the maze's MJCF to a temporary file and keeps it; MuJoCo has loaded the model
    by now, so it is removed here (the file descriptor `mkstemp` opened stays open: OGBench
    drops it).
    """
    check_ogbench_id(env_id)
    import ogbench.locomaze  # noqa: F401  (registers the mazes)

    env = gymnasium.make(env_id, **kwargs)
    Path(env.unwrapped.fullpath).unlink(missing_ok=True)
    return env


@functools.cache
def reference_env(env_id: str) -> gymnasium.Env:
    """One shared env per id for its read-only parts (maze map, tasks, BFS oracle, cell maths).

    Never step it or set its goal: its `MjModel` is the nominal model of `make_env_spec`.
    """
    return make_ogbench_env(env_id)


def ogbench_layout(env: gymnasium.Env, radius: float) -> dict[str, Any]:
    """The maze in `pipeline.envs.maze.env.maze_layout`'s shape, rows listed bottom-up (see module).

    Extra keys: `ogbench_maze_map` (OGBench's own rows) and `row_order` (how they relate).
    """
    maze_map = np.asarray(env.unwrapped.maze_map).astype(int)
    flipped = maze_map[::-1].tolist()
    n_rows, n_cols = maze_map.shape
    x_c = MAZE_OFFSET + MAZE_UNIT / 2
    y_c = MAZE_UNIT * n_rows - MAZE_OFFSET - MAZE_UNIT / 2
    free = [(r, c) for r, row in enumerate(flipped) for c, v in enumerate(row) if v != 1]
    walls = [[r, c] for r, row in enumerate(flipped) for c, v in enumerate(row) if v == 1]
    centers = [[(c + 0.5) * MAZE_UNIT - x_c, y_c - (r + 0.5) * MAZE_UNIT] for r, c in free]
    return {
        "maze_map": flipped,
        "maze_size_scaling": MAZE_UNIT,
        "maze_height": float(env.unwrapped._maze_height * MAZE_UNIT),
        "x_map_center": x_c,
        "y_map_center": y_c,
        "n_rows": n_rows,
        "n_cols": n_cols,
        "free_cells": [[r, c] for r, c in free],
        "wall_cells": walls,
        "free_cell_centers": centers,
        "bounds": [-x_c, -x_c + n_cols * MAZE_UNIT, y_c - n_rows * MAZE_UNIT, y_c],
        "agent_radius": radius,
        "ogbench_maze_map": maze_map.tolist(),
        "row_order": "bottom-up: layout row r is OGBench row n_rows - 1 - r",
    }


def ogbench_cell_xy(ij: tuple[int, int]) -> np.ndarray:
    """Centre `[x, y]` of OGBench cell `(i, j)` (its `ij_to_xy`)."""
    i, j = ij
    return np.array([j * MAZE_UNIT - MAZE_OFFSET, i * MAZE_UNIT - MAZE_OFFSET])


def ogbench_cell(xy: np.ndarray) -> tuple[int, int]:
    """OGBench cell `(i, j)` holding `[x, y]` (its `xy_to_ij`, floored for points off the map)."""
    i = math.floor((float(xy[1]) + MAZE_OFFSET + 0.5 * MAZE_UNIT) / MAZE_UNIT)
    j = math.floor((float(xy[0]) + MAZE_OFFSET + 0.5 * MAZE_UNIT) / MAZE_UNIT)
    return i, j


def ogbench_tasks(env_id: str) -> list[dict[str, Any]]:
    """The maze's evaluation tasks as OGBench defines them: name, init_ij, goal_ij, their xy."""
    return [
        {
            "name": str(t["task_name"]),
            "init_ij": tuple(int(v) for v in t["init_ij"]),
            "goal_ij": tuple(int(v) for v in t["goal_ij"]),
            "init_xy": ogbench_cell_xy(t["init_ij"]),
            "goal_xy": ogbench_cell_xy(t["goal_ij"]),
        }
        for t in reference_env(env_id).unwrapped.task_infos
    ]


# OGBench's healthy torso height (`online-ant-v0`'s termination range), m.
ANT_HEALTHY_Z = (0.2, 1.0)


def ant_fallen(observations):
    """`[...]` bool per ant observation `[..., 29]` (a numpy array or a torch tensor): the torso
    (`qpos[2]` height, `qpos[3:7]` quaternion w, x, y, z) is outside the healthy height range or
    upside down (its z axis pointing below the horizon)."""
    z = observations[..., 2]
    up = torso_up(observations[..., 3:7])
    low, high = ANT_HEALTHY_Z
    return (z < low) | (z > high) | (up < 0.0)


def torso_up(quat):
    """`[...]` z component of the torso's z axis from `[..., 4]` quaternions (w, x, y, z; a numpy
    array or a torch tensor); below 0 the ant is upside down. OGBench's reset noise leaves
    quaternions unnormalized."""
    if not hasattr(quat, "shape"):
        quat = np.asarray(quat, dtype=np.float64)
    return 1.0 - 2.0 * (quat[..., 1] ** 2 + quat[..., 2] ** 2) / (quat**2).sum(-1)


@dataclass(frozen=True, eq=False)
class Teleports:
    """OGBench's teleports (`MazeEnv._teleport_info`): inbound and outbound centres `[n, 2]`, and
    how near an inbound centre a step must end to be moved (1.5 x the teleport radius)."""

    inbound: np.ndarray
    outbound: np.ndarray
    reach: float

    @classmethod
    def of_env(cls, env: gymnasium.Env) -> Teleports | None:
        info = env.unwrapped._teleport_info
        if info is None:
            return None
        inbound = np.array(info["teleport_in_xys"], dtype=np.float64)
        outbound = np.array(info["teleport_out_xys"], dtype=np.float64)
        return cls(inbound, outbound, float(info["teleport_radius"]) * 1.5)

    def inside(self, xy: np.ndarray) -> np.ndarray:
        """`[...]` bool per position `[..., 2]`: within reach of an inbound teleport."""
        xy = np.asarray(xy, dtype=np.float64)[..., None, :2]
        return (np.linalg.norm(xy - self.inbound, axis=-1) <= self.reach).any(axis=-1)

    def destination(self, xy: np.ndarray, rng: np.random.Generator) -> np.ndarray | None:
        """Where an agent at `xy` is moved (one draw from `rng`), or None if it is not moved."""
        if not self.inside(xy):
            return None
        return self.outbound[int(rng.integers(len(self.outbound)))]


@dataclass(frozen=True, eq=False)
class OGBenchMazeSpec(ABC):
    """An OGBench maze (`EnvSpec`); the locomotor's parts are in the subclasses.

    Build it with `OGBenchMazeSpec.create(env_id)` (or `make_env_spec`).

    Attributes (besides `EnvSpec`'s):
        loco: "point" or "ant".
        goal_tolerance: OGBench's success distance (1.0 point, 0.5 ant).
    """

    env_id: str
    layout: dict[str, Any]
    model: mujoco.MjModel
    dt: float
    loco: str
    goal_tolerance: float
    state_dim: int
    action_dim: int
    max_episode_steps: int = EPISODE_STEPS
    goal_dims: tuple[int, ...] = (0, 1)
    teleports: Teleports | None = None
    state_spec: ClassVar[int] = PHYSICS_SPEC

    @classmethod
    def create(cls, env_id: str) -> OGBenchMazeSpec:
        """The spec of OGBench's `env_id` (`pointmaze-medium-v0`, ...)."""
        loco, _ = check_ogbench_id(env_id)
        env = reference_env(env_id)
        model = env.unwrapped.model
        kind = OGBenchPointMazeSpec if loco == "point" else OGBenchAntMazeSpec
        return kind(
            env_id=env_id,
            layout=ogbench_layout(env, AGENT_RADIUS[loco]),
            model=model,
            dt=float(env.unwrapped.dt),
            loco=loco,
            goal_tolerance=GOAL_TOLERANCE[loco],
            state_dim=int(env.observation_space.shape[0]),
            action_dim=int(env.action_space.shape[0]),
            teleports=Teleports.of_env(env),
        )

    @property
    def physics_dim(self) -> int:
        """`[time, qpos, qvel]` (`mjSTATE_FULLPHYSICS`): 5 for the point, 30 for the ant."""
        return int(mujoco.mj_stateSize(self.model, PHYSICS_SPEC))

    def set_physics_state(
        self, data: mujoco.MjData, state: np.ndarray, model: mujoco.MjModel | None = None
    ) -> None:
        """`[time, qpos, qvel]`; the solver's warm start zeroed, as after a reset."""
        restore_physics(model or self.model, data, state, PHYSICS_SPEC)

    @abstractmethod
    def start_observation(self, xy: np.ndarray) -> np.ndarray:
        """The observation of a task start at `xy` (what `MazeEnv.reset` leaves, noise aside)."""

    def teleport(
        self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator
    ) -> None:
        """Before a step: move an agent that the last step left at an inbound teleport to an
        outbound one (`MazeEnv.step`'s teleport, deferred; module docstring)."""
        if self.teleports is None:
            return
        out = self.teleports.destination(data.qpos[:2], rng)
        if out is not None:
            data.qpos[:2] = out  # `set_xy`: qvel kept, then `set_state`'s forward pass
            mujoco.mj_forward(model, data)

    @abstractmethod
    def observe(self, data: mujoco.MjData) -> np.ndarray:
        """The observation of the simulator state `data`."""

    @abstractmethod
    def set_observation(self, data: mujoco.MjData, observation: np.ndarray) -> None:
        """Put `observation` into the simulator state `data`."""

    @abstractmethod
    def control_step(self, model: mujoco.MjModel, data: mujoco.MjData, action: np.ndarray) -> None:
        """One control step of `action` (the env's `step`, physics only)."""


class OGBenchPointMazeSpec(OGBenchMazeSpec):
    """OGBench's point: observation `[x, y]`, displacement action `[dx, dy]` (module docstring)."""

    def start_observation(self, xy: np.ndarray) -> np.ndarray:
        """`[x, y]`: the point's whole state."""
        return np.asarray(xy, dtype=np.float64)[:2].copy()

    def observe(self, data: mujoco.MjData) -> np.ndarray:
        """`[x, y]` = qpos (`PointEnv.get_ob`)."""
        return data.qpos.copy()

    def set_observation(self, data: mujoco.MjData, observation: np.ndarray) -> None:
        """qpos = `[x, y]`, qvel = 0 (the next step zeroes qvel anyway)."""
        data.qpos[:] = observation[:2]
        data.qvel[:] = 0.0

    def control_step(self, model: mujoco.MjModel, data: mujoco.MjData, action: np.ndarray) -> None:
        """`PointEnv.step` bit for bit, after OGBench's evaluation clip of the action to [-1, 1]:
        qpos += 0.2 * action, qvel = 0, 5 MuJoCo steps."""
        ax, ay = (min(max(float(a), -1.0), 1.0) for a in action)
        qpos = data.qpos
        x, y = qpos.tolist()
        qpos[0] = x + POINT_STEP * ax
        qpos[1] = y + POINT_STEP * ay
        data.qvel[:] = 0.0
        mujoco.mj_step(model, data, nstep=5)


class OGBenchAntMazeSpec(OGBenchMazeSpec):
    """OGBench's ant: observation `qpos + qvel` (15 + 14), joint torques (8) through gear 30."""

    def start_observation(self, xy: np.ndarray) -> np.ndarray:
        """The ant standing at rest at `xy` (its `init_qpos` with x, y replaced)."""
        qpos = np.array(self.model.qpos0, dtype=np.float64)
        qpos[:2] = np.asarray(xy, dtype=np.float64)[:2]
        return np.concatenate([qpos, np.zeros(self.model.nv)])

    def observe(self, data: mujoco.MjData) -> np.ndarray:
        """`[qpos, qvel]` (`AntEnv.get_ob`)."""
        return np.concatenate([data.qpos, data.qvel])

    def set_observation(self, data: mujoco.MjData, observation: np.ndarray) -> None:
        nq = self.model.nq
        data.qpos[:] = observation[:nq]
        data.qvel[:] = observation[nq : nq + self.model.nv]

    def fallen(self, observations):
        """`[...]` bool per observation `[..., 29]` (numpy or torch): torso outside OGBench's
        healthy height or upside down (`ant_fallen`). A flipped ant cannot right itself: deploy
        reports these episodes, and `deploy.planner.fall_penalty` keeps plans from them."""
        return ant_fallen(observations)

    def control_step(self, model: mujoco.MjModel, data: mujoco.MjData, action: np.ndarray) -> None:
        """`MujocoEnv.do_simulation` (ctrl = action clipped to [-1, 1], 5 MuJoCo steps,
        `mj_rnePostConstraint`), as `AntEnv.step` runs it."""
        data.ctrl[:] = np.clip(action, -1.0, 1.0)
        mujoco.mj_step(model, data, nstep=5)
        mujoco.mj_rnePostConstraint(model, data)
