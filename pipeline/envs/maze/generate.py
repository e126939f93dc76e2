"""Demonstrations from the scripted expert, made the way D4RL made maze2d.

One continuous simulation (reset once, at a random free cell) in which the expert chases random
goals forever; the stream is cut into `n_episodes` episodes of `episode_steps` steps, so episode
k + 1 starts exactly where episode k ended and `time` runs on one clock (step count * dt).
"""

from __future__ import annotations

import importlib.metadata
from collections.abc import Iterator
from typing import Any

import mujoco
import numpy as np
from tqdm import tqdm

from pipeline.dataset import DatasetInfo, Episode
from pipeline.envs.disturbance import Pushes, draw_force, push_rng, pushed_step
from pipeline.envs.maze.env import make_maze_env, maze_layout, point_env, step_point_mass
from pipeline.envs.maze.expert import ExpertConfig, WaypointExpert
from pipeline.envs.physics import PHYSICS_SPEC
from pipeline.errors import UserError

STATE_NAMES = ["x", "y", "vx", "vy"]
STATE_UNITS = ["m", "m", "m/s", "m/s"]
ACTION_NAMES = ["fx", "fy"]
# Actions are dimensionless: the motor's ctrl in [-1, 1] (times gear 100 it is a force in N).
ACTION_UNITS = ["1", "1"]
# Progress bar refresh period, in steps.
_BAR_EVERY = 1000


def _check_sizes(n_episodes: int, episode_steps: int, seed: int) -> None:
    """Raise `UserError` on non-positive episode counts or lengths, or a bad seed."""
    for name, value, low in (("n_episodes", n_episodes, 1), ("episode_steps", episode_steps, 1)):
        if not isinstance(value, int | np.integer) or value < low:
            raise UserError(f"{name} must be an integer >= {low}, got {value!r}")
    if not isinstance(seed, int | np.integer) or seed < 0:
        raise UserError(f"seed must be an integer >= 0, got {seed!r}")


def _show_goal(env, expert: WaypointExpert) -> None:
    """Mirror the expert's goal into the env (its `goal` and the red target site, for renders)."""
    env.unwrapped.goal = expert.goal
    env.unwrapped.update_target_site_pos()


def generate_episodes(
    env_id: str,
    n_episodes: int,
    episode_steps: int,
    seed: int,
    expert: ExpertConfig,
    progress: bool = True,
    maze_map: list[list[int | str]] | None = None,
    disturbance: Pushes | None = None,
) -> Iterator[Episode]:
    """Run the expert in one continuous simulation and yield it as consecutive episodes.

    Deterministic given `seed`: it seeds the env reset (start position) and the expert's
    Generator (goals, waypoint jitter, action noise).

    Args:
        env_id: A supported PointMaze id (see `SUPPORTED_ENVS`).
        n_episodes: Number of episodes to yield.
        episode_steps: Steps N per episode.
        seed: Random seed.
        expert: Expert gains and noise.
        progress: Show a tqdm bar over the total number of steps.
        maze_map: Custom map instead of the env's own (e.g. a tiny maze in tests).
        disturbance: Random pushes on the ball (`pipeline.envs.disturbance`), drawn from their
            own generator (seeded from `seed`); None: none, and the data is as without them.

    Returns:
        An iterator over `Episode`s with observations `[N, 4]` (x, y, vx, vy before the step),
        actions `[N, 2]` (as sent: after noise and clipping), time `[N]`, physics `[N, 5]` (full
        MuJoCo state before the step), goals `[N, 2]` (the expert's goal at step t) and
        goal_reached `[N]` (True where the step's action brought the ball within `goal_radius`).
        No rewards or terminals. Arguments are checked at the call, not at the first `next`.
    """
    _check_sizes(n_episodes, episode_steps, seed)
    env = make_maze_env(env_id, maze_map)  # validates here, not at the first next()
    pushes = disturbance or Pushes()
    return _generate(env, env_id, n_episodes, episode_steps, int(seed), expert, progress, pushes)


def _generate(
    env,
    env_id: str,
    n_episodes: int,
    episode_steps: int,
    seed: int,
    expert: ExpertConfig,
    progress: bool,
    pushes: Pushes,
) -> Iterator[Episode]:
    """The body of `generate_episodes`, run lazily; closes `env` when done."""
    try:
        env.reset(seed=seed)
        pe = point_env(env)
        model, data = pe.model, pe.data
        physics_dim = mujoco.mj_stateSize(model, PHYSICS_SPEC)
        nq, nv = model.nq, model.nv
        if (nq, nv, physics_dim) != (2, 2, 5):
            raise RuntimeError(f"unexpected point mass model: nq={nq} nv={nv} state={physics_dim}")
        dt = float(pe.dt)
        bot = WaypointExpert(maze_layout(env), expert, np.random.default_rng(seed))
        push = _Push(pushes, push_rng(seed), dt)
        bot.new_goal(*data.qpos.tolist())
        _show_goal(env, bot)
        total = n_episodes * episode_steps
        with tqdm(total=total, disable=not progress, unit="step", desc=env_id) as bar:
            for k in range(n_episodes):
                physics, actions, goals, reached = _run(model, data, bot, episode_steps, bar, push)
                _show_goal(env, bot)
                yield Episode(
                    index=k,
                    observations=physics[:, 1 : 1 + nq + nv].copy(),
                    actions=actions,
                    time=(k * episode_steps + np.arange(episode_steps)) * dt,
                    physics=physics,
                    goals=goals,
                    goal_reached=reached,
                )
    finally:
        env.close()


class _Push:
    """The data stream's pushes: `force()` for each step in turn."""

    def __init__(self, pushes: Pushes, rng: np.random.Generator, dt: float):
        self.pushes, self.rng, self.dt = pushes, rng, dt

    def force(self) -> tuple[float, float] | None:
        return draw_force(self.pushes, self.rng, self.dt)


def _run(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    bot: WaypointExpert,
    n: int,
    bar: tqdm,
    push: _Push,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Simulate `n` expert steps from the current state; the hot loop of data generation.

    Returns:
        physics `[n, 5]` (before each step), actions `[n, 2]`, goals `[n, 2]`, reached `[n]`.
    """
    physics = np.empty((n, mujoco.mj_stateSize(model, PHYSICS_SPEC)))
    actions = np.empty((n, 2))
    goals = np.empty((n, 2))
    reached = np.zeros(n, dtype=bool)
    qpos = data.qpos
    for t in range(n):
        row = physics[t]
        mujoco.mj_getState(model, data, row, PHYSICS_SPEC)
        _, x, y, vx, vy = row.tolist()
        goals[t] = bot.goal_x, bot.goal_y
        action = bot.act(x, y, vx, vy)
        actions[t] = action
        if push.pushes.active:
            pushed_step(step_point_mass, model, data, action, push.force())
        else:
            step_point_mass(model, data, action)
        x, y = qpos.tolist()
        reached[t] = bot.update(x, y)
        if (t + 1) % _BAR_EVERY == 0:
            bar.update(_BAR_EVERY)
    bar.update(n % _BAR_EVERY)
    return physics, actions, goals, reached


def _versions() -> dict[str, str]:
    """Versions of the packages that determine the generated data."""
    names = ("gymnasium", "gymnasium_robotics", "mujoco", "numpy")
    return {name: importlib.metadata.version(name) for name in names}


def dataset_info(
    env_id: str,
    name: str,
    seed: int,
    expert: ExpertConfig,
    n_episodes: int,
    episode_steps: int,
    maze_map: list[list[int | str]] | None = None,
    disturbance: Pushes | None = None,
) -> DatasetInfo:
    """Metadata of a dataset made by `generate_episodes` with the same arguments.

    `env_kwargs` holds the maze map (so `make_maze_env(env_id, **env_kwargs)` or
    `gym.make(env_id, **env_kwargs)` rebuilds the env); `generator` holds the expert config,
    the episode layout and the full `maze_layout` (for drawing walls without MuJoCo).
    """
    _check_sizes(n_episodes, episode_steps, seed)
    env = make_maze_env(env_id, maze_map)
    try:
        layout = maze_layout(env)
        pe = point_env(env)
        control_period = float(pe.dt)
        physics_dim = int(mujoco.mj_stateSize(pe.model, PHYSICS_SPEC))
    finally:
        env.close()
    generator: dict[str, Any] = {
        "expert": expert.to_dict(),
        "n_episodes": int(n_episodes),
        "episode_steps": int(episode_steps),
        "planner": "bfs",
        "continuous": True,
        "maze_layout": layout,
    }
    if disturbance is not None and disturbance.active:  # absent: datasets stay as they were
        generator["disturbance"] = disturbance.to_dict()
    return DatasetInfo(
        name=name,
        source="maze",
        env_id=env_id,
        state_names=list(STATE_NAMES),
        action_names=list(ACTION_NAMES),
        state_units=list(STATE_UNITS),
        action_units=list(ACTION_UNITS),
        control_period=control_period,
        physics_dim=physics_dim,
        goal_dim=2,
        seed=int(seed),
        env_kwargs={"maze_map": layout["maze_map"]},
        generator=generator,
        versions=_versions(),
    )
