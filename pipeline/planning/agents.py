"""What the episode runner drives, and the agents that do not plan.

Every agent (`SkillMPC`: OPOSM; `LowLevelMPC`: LLP; `PolicyAgent`: GCBC; `ExpertAgent`: the data's
scripted controller) serves B environment slots through one interface, so all of them run through
the same episodes, tasks, seeds, success rule, report and recordings. Planning agents are asked to
`replan` every so many steps (the runner's `RunConfig.replan_every`); static policies never are.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np
import torch

from pipeline.envs.maze.expert import ExpertConfig, WaypointExpert
from pipeline.model.policy import GaussianPolicy
from pipeline.planning.noise import normal, problem_keys, substream


class PlanLike(Protocol):
    """What the runner records of a plan: predicted `states [A, P + 1, sd]`, `cost [A]`."""

    states: torch.Tensor
    cost: torch.Tensor


class Agent(Protocol):
    """B environment slots' controller (see the module docstring).

    Attributes:
        name: The agent's name in reports and recordings (`deploy.agents`).
    """

    name: str

    def reset(self, goals: np.ndarray, seeds: Sequence[int]) -> None:
        """Start new episodes in all B slots: goals `[B, G]`, one seed per episode."""
        ...

    def replan(self, rows: np.ndarray, states: np.ndarray) -> PlanLike:
        """Plan for slots `rows [A]` from their states `[A, sd]` (planning agents only)."""
        ...

    def act(self, rows: np.ndarray, states: np.ndarray) -> np.ndarray:
        """Actions `[A, ad]` (raw units, float64) for slots `rows [A]` in states `[A, sd]`."""
        ...


class PolicyAgent:
    """A goal-conditioned policy p(a | s, g) run closed loop (GCBC): one forward pass per step.

    Args:
        policy: The goal-conditioned Gaussian policy.
        sample_actions: Sample actions (each episode from its own stream) instead of the mean.
        name: The agent's name.
    """

    def __init__(self, policy: GaussianPolicy, sample_actions: bool = False, name: str = "gcbc"):
        if not policy.goal_conditioned:
            raise ValueError("PolicyAgent needs a goal-conditioned policy p(a | s, g)")
        self.policy = policy
        self.sample_actions = sample_actions
        self.name = name
        self.device = policy.state_mean.device
        self._goals = torch.zeros(0)
        self._keys = torch.zeros(0, dtype=torch.long)  # [B] action-noise stream per slot
        self._steps = torch.zeros(0, dtype=torch.long)  # [B] actions taken so far per slot

    def reset(self, goals: np.ndarray, seeds: Sequence[int]) -> None:
        self._goals = torch.as_tensor(goals, dtype=torch.float32, device=self.device)
        self._keys = problem_keys(seeds, self.device)
        self._steps = torch.zeros(len(seeds), dtype=torch.long, device=self.device)

    def replan(self, rows: np.ndarray, states: np.ndarray) -> Any:
        raise RuntimeError("a static policy does not plan (run it with replan_every=None)")

    @torch.no_grad()
    def act(self, rows: np.ndarray, states: np.ndarray) -> np.ndarray:
        s = torch.as_tensor(states, dtype=torch.float32, device=self.device)
        idx = torch.as_tensor(rows, dtype=torch.long, device=self.device)
        mean, std = self.policy.action_stats(s, self._goals[idx])
        if self.sample_actions:  # each episode from its own stream, on the device
            mean = mean + std * normal(substream(self._keys[idx], self._steps[idx]), mean.shape[1:])
            self._steps[idx] += 1
        return mean.double().cpu().numpy()


class ExpertAgent:
    """The scripted maze expert (D4RL's waypoint planner + PD) steering to each episode's goal.

    One `WaypointExpert` per slot with the episode's seed (action noise and waypoint jitter); it
    plans its path of cells from the start state at its first step and follows it to the goal
    (it never switches to a new random goal, as it does while making data).

    Args:
        layout: The maze (`EnvSpec.layout`).
        config: Gains and noise (the dataset's, for "the controller that made the data").
        name: The agent's name.
    """

    def __init__(self, layout: dict[str, Any], config: ExpertConfig, name: str = "expert"):
        self.layout = layout
        self.config = config
        self.name = name
        self._experts: list[WaypointExpert] = []
        self._goals = np.zeros((0, 2))
        self._started = np.zeros(0, dtype=bool)

    def reset(self, goals: np.ndarray, seeds: Sequence[int]) -> None:
        self._experts = [
            WaypointExpert(self.layout, self.config, np.random.default_rng(int(s))) for s in seeds
        ]
        self._goals = np.asarray(goals, dtype=np.float64)
        self._started = np.zeros(len(seeds), dtype=bool)

    def replan(self, rows: np.ndarray, states: np.ndarray) -> Any:
        raise RuntimeError("the expert does not plan with a model (run it with replan_every=None)")

    def act(self, rows: np.ndarray, states: np.ndarray) -> np.ndarray:
        out = np.empty((len(rows), 2))
        for j, (i, s) in enumerate(zip(rows.tolist(), states, strict=True)):
            expert, (x, y, vx, vy) = self._experts[i], map(float, s[:4])
            if not self._started[i]:
                expert.set_goal(x, y, *map(float, self._goals[i]))
                self._started[i] = True
            out[j] = expert.act(x, y, vx, vy)
        return out
