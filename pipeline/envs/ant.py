"""OGBench's ant: the direction-commanded locomotion task its expert learns, and its mazes.

Both use OGBench's `ant.xml` (D4RL's ant: gear 30, dt 0.02 with RK4, 5 substeps -> 0.1 s a step;
the `online_locomotion` and `locomaze` copies differ only in colours, textures and cameras).

The expert's observation is the ant's state without its x-y position (qpos[2:] 13 + qvel 14 = 27)
followed by the commanded unit direction (2): 29 numbers. `online-ant-v0` already drops x-y, and
OGBench's `GymXYWrapper` appends the direction and rewards the displacement along it; in the mazes
the direction points to the BFS oracle's next cell (OGBench's `generate_locomaze.py`).

OGBench draws directions, start noise and goal noise from numpy's global generator; `global_seed`
seeds it for a block and puts the caller's state back afterwards.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import gymnasium
import numpy as np

from pipeline.envs.ogbench import torso_up

DIRECTION_ENV_ID = "online-ant-v0"
STATE_DIM = 29  # qpos 15 + qvel 14
EXPERT_OBS_DIM = 29  # state without x-y (27) + unit direction (2)
ACTION_DIM = 8


def make_direction_env(
    resample_interval: int = 100, max_episode_steps: int = 1000
) -> gymnasium.Env:
    """`online-ant-v0` in OGBench's `GymXYWrapper`: observation [27 state, 2 direction].

    Reward = x-y displacement of the torso along the direction during the step (m); a new
    direction every `resample_interval` steps; the episode ends when the ant is unhealthy (torso
    height outside [0.2, 1.0]) or after `max_episode_steps`.
    """
    import ogbench.online_locomotion  # noqa: F401  (registers online-ant-v0)
    from ogbench.online_locomotion.wrappers import GymXYWrapper

    env = gymnasium.make(DIRECTION_ENV_ID, max_episode_steps=max_episode_steps)
    return GymXYWrapper(env, resample_interval=resample_interval)


class UpsideDownEnd(gymnasium.Wrapper):
    """Ends the episode (terminated) when the ant is upside down, while `enabled`.

    `flips` counts the episodes it ended; the trainer switches it per `sac.phases` entry.
    """

    def __init__(self, env: gymnasium.Env, enabled: bool = False) -> None:
        super().__init__(env)
        self.enabled = enabled
        self.flips = 0

    def step(self, action):  # type: ignore[no-untyped-def]
        obs, reward, terminated, truncated, info = self.env.step(action)
        if self.enabled and not terminated and torso_up(self.unwrapped.data.qpos[3:7]) < 0.0:
            terminated = True
            self.flips += 1
        return obs, reward, terminated, truncated, info


def make_ant_maze(env_id: str, max_episode_steps: int = 1000) -> gymnasium.Env:
    """An OGBench ant maze (`antmaze-medium-v0`, ...): state observation, ends on success."""
    import ogbench.locomaze  # noqa: F401  (registers the mazes)

    return gymnasium.make(env_id, max_episode_steps=max_episode_steps)


def expert_observation(state: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """[29] ant state (qpos + qvel) and [2] unit direction -> [29] expert observation."""
    return np.concatenate([state[2:], direction])


def oracle_direction(maze: gymnasium.Env) -> np.ndarray:
    """Unit direction from the ant to the next cell of the BFS path to the maze's current goal."""
    unwrapped = maze.unwrapped
    xy = unwrapped.get_xy()
    subgoal, _ = unwrapped.get_oracle_subgoal(xy, unwrapped.cur_goal_xy)
    delta = np.asarray(subgoal, dtype=np.float64) - xy
    return delta / (np.linalg.norm(delta) + 1e-6)


@contextlib.contextmanager
def global_seed(seed: int) -> Iterator[None]:
    """Seed numpy's global generator (OGBench's source of randomness) inside the block."""
    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(saved)
