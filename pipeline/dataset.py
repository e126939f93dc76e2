"""In-memory form of a demonstration dataset: what sources produce and what the MCAP reader yields.

Conventions (shared by every source, the MCAP format and the segment stage):

- An episode is a physically continuous sequence of N steps. Step t holds the observation s_t seen
  *before* acting and the action a_t taken from it, so `observations[t + 1]` is the result of
  `actions[t]`. (Sources that store N + 1 observations, like Minari, drop the final one.)
- `time` is the simulated time of step t in seconds, measured on one clock for the whole dataset:
  episode k starts where episode k - 1 ended (for the built-in expert, which drives one continuous
  simulation, this is the real simulated time).
- Optional per-step arrays are `None` when a source does not have them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import ConfigDict, with_config

from pipeline.readback import Count, PositiveFinite


@dataclass
class Episode:
    """One physically continuous episode of N steps.

    Attributes:
        index: Episode index within the dataset (0, 1, 2, ... in file order).
        observations: `[N, state_dim]` float64, s_t before the action.
        actions: `[N, action_dim]` float64, a_t.
        time: `[N]` float64, simulated time in seconds on the dataset clock.
        physics: `[N, physics_dim]` float64 MuJoCo full physics state (`mjSTATE_FULLPHYSICS`) at
            step t, enough to restore the simulator exactly; None if the source has none.
        goals: `[N, goal_dim]` float64, the goal the demonstrator pursued at step t.
        goal_reached: `[N]` bool, True at the step where the demonstrator reached its goal.
        rewards: `[N]` float64 reward for (s_t, a_t).
        terminals: `[N]` bool, True if the environment terminated after step t.
    """

    index: int
    observations: np.ndarray
    actions: np.ndarray
    time: np.ndarray
    physics: np.ndarray | None = None
    goals: np.ndarray | None = None
    goal_reached: np.ndarray | None = None
    rewards: np.ndarray | None = None
    terminals: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.observations.shape[0])


@with_config(ConfigDict(extra="forbid"))  # read back (segments.json): an unknown key is an error
@dataclass
class DatasetInfo:
    """Provenance and what later stages need, stored as MCAP metadata records.

    Attributes:
        name: Dataset name (also the MCAP file stem).
        source: Where the demonstrations came from: "maze" (built-in expert), "lerobot", "d4rl",
            "minari".
        env_id: Gymnasium id of the environment that can simulate the data, or "" if none.
        state_names: One name per state dimension, e.g. ["x", "y", "vx", "vy"].
        action_names: One name per action dimension.
        state_units: One unit per state dimension, e.g. ["m", "m", "m/s", "m/s"].
        action_units: One unit per action dimension.
        control_period: Seconds between two steps.
        physics_dim: Length of the per-step physics state (0 if none is recorded).
        goal_dim: Length of the per-step goal (0 if none).
        seed: Seed the data was generated with (None for imported data).
        env_kwargs: Keyword arguments to rebuild the environment (`gym.make(env_id, **env_kwargs)`),
            e.g. the maze map.
        generator: Parameters of the generator or importer (expert gains, noise, source path...).
        versions: Package versions that produced the file.
    """

    name: str
    source: str
    env_id: str
    state_names: list[str]
    action_names: list[str]
    state_units: list[str]
    action_units: list[str]
    control_period: PositiveFinite
    physics_dim: Count = 0
    goal_dim: Count = 0
    seed: int | None = None
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    generator: dict[str, Any] = field(default_factory=dict)
    versions: dict[str, str] = field(default_factory=dict)

    @property
    def state_dim(self) -> int:
        return len(self.state_names)

    @property
    def action_dim(self) -> int:
        return len(self.action_names)
