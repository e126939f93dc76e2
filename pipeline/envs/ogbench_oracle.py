"""OGBench's data-generating controller for its point mazes, and the same as a deploy agent.

`generate_locomaze.py` (OGBench's repository) drives the point with the unit direction from the
point to its BFS oracle subgoal (`MazeEnv.get_oracle_subgoal`: the centre of the neighbouring
cell one step closer to the goal cell, or of the current cell once there), plus Gaussian noise
(std 0.5 for the point), clipped to [-1, 1]: `direction = (subgoal - xy) / (|subgoal - xy| +
1e-6)`. The BFS is OGBench's own, called on the maze's reference env; its answer depends only on
the two cells, so it is memoized per (cell, goal cell).

The ant's oracle feeds this direction to our direction-commanded ant expert instead (issue 19:
`experts/ant/`), with Gaussian noise on its actions (OGBench's ant data: 0.2).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from pipeline.ant_expert.actor import DirectionActor
from pipeline.envs.ant import expert_observation
from pipeline.envs.ogbench import check_ogbench_id, ogbench_cell, reference_env
from pipeline.errors import UserError

# OGBench's action noise for the point's datasets (`commands.sh`: `--noise=0.5`).
POINT_NOISE = 0.5


class BFSOracle:
    """Unit directions to OGBench's BFS subgoal in one maze (`env_id`)."""

    def __init__(self, env_id: str):
        check_ogbench_id(env_id)
        self.env_id = env_id
        self._maze = reference_env(env_id).unwrapped
        self._subgoals: dict[tuple[tuple[int, int], tuple[int, int]], np.ndarray] = {}

    def subgoal(self, xy: np.ndarray, goal_xy: np.ndarray) -> np.ndarray:
        """`[x, y]` of OGBench's oracle subgoal from `xy` towards `goal_xy`."""
        key = (ogbench_cell(xy), ogbench_cell(goal_xy))
        found = self._subgoals.get(key)
        if found is None:
            found, _ = self._maze.get_oracle_subgoal(np.asarray(xy), np.asarray(goal_xy))
            found = self._subgoals[key] = np.asarray(found, dtype=np.float64)
        return found

    def direction(self, xy: np.ndarray, goal_xy: np.ndarray) -> np.ndarray:
        """Unit vector `[2]` from `xy` to the subgoal (`generate_locomaze.py`'s formula)."""
        delta = self.subgoal(xy, goal_xy) - np.asarray(xy, dtype=np.float64)
        return delta / (np.linalg.norm(delta) + 1e-6)

    def point_action(
        self, xy: np.ndarray, goal_xy: np.ndarray, noise: float, rng: np.random.Generator
    ) -> np.ndarray:
        """The point's action: direction + N(0, noise^2) per axis, clipped to [-1, 1]."""
        action = self.direction(xy, goal_xy) + rng.normal(0.0, noise, 2)
        return np.clip(action, -1.0, 1.0)


class OGBenchOracleAgent:
    """`BFSOracle` driving the robot to each episode's goal, as a deploy agent (`Agent`): the
    point takes the direction as its action; the ant's `actor` walks it (observation: the ant's
    state without x, y, then the direction).

    Each episode draws its action noise from its own seed. Args: `env_id`, `noise` (action noise
    std), `name`, `actor` (the ant's direction-commanded expert; ant mazes only).
    """

    def __init__(
        self,
        env_id: str,
        noise: float = POINT_NOISE,
        name: str = "expert",
        actor: DirectionActor | None = None,
    ):
        loco, _ = check_ogbench_id(env_id)
        if loco not in ("point", "ant"):
            raise UserError(f"the expert agent of {env_id} needs a {loco} policy we do not have")
        if loco == "ant" and actor is None:
            raise UserError(
                f"the expert agent of {env_id} needs the ant expert that made the data "
                "(experts/ant/actor.safetensors: `oposm expert train ant`)"
            )
        self.oracle = BFSOracle(env_id)
        self.actor = actor if loco == "ant" else None
        self.noise = float(noise)
        self.name = name
        self._goals = np.zeros((0, 2))
        self._rngs: list[np.random.Generator] = []

    def reset(self, goals: np.ndarray, seeds: Sequence[int]) -> None:
        self._goals = np.asarray(goals, dtype=np.float64)
        self._rngs = [np.random.default_rng(int(s)) for s in seeds]

    def replan(self, rows: np.ndarray, states: np.ndarray) -> Any:
        raise RuntimeError("the oracle does not plan with a model (run it with replan_every=None)")

    def act(self, rows: np.ndarray, states: np.ndarray) -> np.ndarray:
        pairs = list(zip(rows.tolist(), states, strict=True))
        if self.actor is None:
            return np.stack(
                [
                    self.oracle.point_action(s[:2], self._goals[i], self.noise, self._rngs[i])
                    for i, s in pairs
                ]  # fmt: skip
            )
        obs = np.stack(
            [expert_observation(s, self.oracle.direction(s[:2], self._goals[i])) for i, s in pairs]
        )
        actions = self.actor.act(obs).astype(np.float64)
        if self.noise > 0:
            noise = np.stack([self._rngs[i].normal(0.0, self.noise, actions.shape[1])
                              for i, _ in pairs])  # fmt: skip
            actions = np.clip(actions + noise, self.actor.spec.action_low,
                              self.actor.spec.action_high)  # fmt: skip
        return actions
