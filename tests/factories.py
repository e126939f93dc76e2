"""Small real datasets built in memory, shared by the tests (`from factories import ...`)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.dataset import DatasetInfo, Episode
from pipeline.errors import UserError


def make_info(name: str = "synthetic", physics_dim: int = 5) -> DatasetInfo:
    return DatasetInfo(
        name=name,
        source="maze",
        env_id="PointMaze_Medium-v3",
        state_names=["x", "y", "vx", "vy"],
        action_names=["fx", "fy"],
        state_units=["m", "m", "m/s", "m/s"],
        action_units=["1", "1"],
        control_period=0.01,
        physics_dim=physics_dim,
        goal_dim=2,
        seed=0,
    )


def make_episodes(lengths: list[int], seed: int = 0, physics_dim: int = 5) -> list[Episode]:
    """Episodes whose states encode (episode, step) so tests can tell where a window came from:
    state[:, 0] = episode index, state[:, 1] = step within the episode."""
    rng = np.random.default_rng(seed)
    episodes, t0 = [], 0.0
    for i, n in enumerate(lengths):
        obs = np.stack([np.full(n, i), np.arange(n), rng.normal(size=n), rng.normal(size=n)], 1)
        episodes.append(
            Episode(
                index=i,
                observations=obs.astype(np.float64),
                actions=rng.uniform(-1, 1, size=(n, 2)),
                time=t0 + 0.01 * np.arange(n),
                physics=rng.normal(size=(n, physics_dim)) if physics_dim else None,
                goals=rng.normal(size=(n, 2)),
                goal_reached=rng.random(n) < 0.01,
            )
        )
        t0 += 0.01 * n
    return episodes


def make_skill_episodes(n_episodes: int, length: int, chunk: int = 10, seed: int = 0):
    """A synthetic skill world: a point whose action is constant for `chunk` steps (a "skill"),
    s = [x, y, vx, vy], x_{t+1} = x_t + 0.05 a_t, v = a_t. Where a window ends depends on the
    actions the skill takes, so a skill model can predict s_T far better than s_T = s_0."""
    rng = np.random.default_rng(seed)
    episodes, t0 = [], 0.0
    for i in range(n_episodes):
        n_chunks = -(-length // chunk)
        directions = rng.uniform(-1, 1, size=(n_chunks, 2))
        actions = np.repeat(directions, chunk, axis=0)[:length]
        actions = actions + 0.05 * rng.normal(size=actions.shape)
        pos = np.cumsum(np.vstack([rng.uniform(-1, 1, size=(1, 2)), 0.05 * actions[:-1]]), 0)
        vel = np.vstack([np.zeros((1, 2)), actions[:-1]])
        episodes.append(
            Episode(
                index=i,
                observations=np.hstack([pos, vel]),
                actions=actions,
                time=t0 + 0.01 * np.arange(length),
            )
        )
        t0 += 0.01 * length
    return episodes


def one_line_error(call) -> str:
    """The message of the `UserError` that `call()` raises, checked to be one line."""
    with pytest.raises(UserError) as err:
        call()
    message = str(err.value)
    assert "\n" not in message
    return message
