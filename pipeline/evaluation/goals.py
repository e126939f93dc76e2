"""How an evaluation episode measures its distance to the goal and judges success.

One rule per environment (`GoalRule.of_spec`), the same one the planners' `GoalCost` is built
from (dims and scale), so what a plan aims at and what the report counts agree:

- the mazes: the distance is the L2 norm of `state[goal_dims] - goal` in metres, success is
  being within `deploy.success_radius` (and gymnasium-robotics' 0.45 reported beside it);
- OGBench's manipulation envs: the distance is over `(state[goal_dims] - goal) / goal_scale`
  (each dim in units of its success tolerance: 1 is "at the tolerance"), and success is
  OGBench's own rule (`ManipSpaceSpec.goal_reached`: every cube within 0.04 m of its goal, the
  scene's buttons, drawer and window in their goal states), whatever the radius;
- the Franka kitchen: the distance as in manipulation (each dim in units of the env's 0.3), and
  success is D4RL's: a goal of several subtasks (`subtasks`: `KitchenSpec.subtasks_reached`,
  each element within 0.3 of its goal) is reached once every subtask has been complete at some
  step of the episode, not necessarily all at once (the env removes a completed subtask); the
  episode's score is the share of its subtasks completed (`EpisodeResult.score`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class GoalRule:
    """Distance and success of states against goals.

    Attributes:
        dims: The state dims a goal `[G]` gives.
        scale: `[G]` divisors of each dim's difference, or None (raw units).
        reached: `(states [..., sd], goals [..., G]) -> bool [...]`, the environment's own
            success test; None: within the radius.
        subtasks: `(states [..., sd], goals [..., G]) -> bool [..., K]`, each of a goal's K
            subtasks complete (the kitchen); None: a goal is one thing. With it an episode
            succeeds once each subtask has been complete at some step (module docstring).
    """

    dims: tuple[int, ...]
    scale: tuple[float, ...] | None = None
    reached: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
    subtasks: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None

    @classmethod
    def of_spec(cls, spec: Any) -> GoalRule:
        """The rule of an `EnvSpec`: its `goal_dims`, and its `goal_scale`, `goal_reached` and
        `subtasks_reached` where it has them (the manipulation envs, the kitchen)."""
        scale = getattr(spec, "goal_scale", None)
        return cls(
            tuple(spec.goal_dims),
            None if scale is None else tuple(scale),
            getattr(spec, "goal_reached", None),
            getattr(spec, "subtasks_reached", None),
        )

    @property
    def unit(self) -> str:
        """What a distance is measured in, for reports."""
        return "m" if self.scale is None else "success tolerances"

    def distance(self, state: np.ndarray, goal: np.ndarray) -> float:
        """The distance of one state `[sd]` from its goal `[G]`."""
        diff = state[list(self.dims)] - goal
        if self.scale is not None:
            diff = diff / np.asarray(self.scale)
        return float(np.linalg.norm(diff))

    def success(self, state: np.ndarray, goal: np.ndarray, distance: float, radius: float) -> bool:
        """Whether one state `[sd]` at `distance` reaches its goal `[G]` (within `radius`,
        unless the environment has its own rule)."""
        if self.reached is not None:
            return bool(self.reached(state, goal))
        return distance <= radius
