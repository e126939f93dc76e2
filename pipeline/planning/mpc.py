"""Model-predictive control with skills (paper §3): plan, execute the first skill for tau steps with
the low-level policy, replan from the state reached.

The agent drives a batch of environment slots. Each slot has its own random streams (CEM noise and
action noise), seeded per episode, so what happens in one episode does not depend on the others
sharing the batch. `replan` and `act` take the slots to serve (`rows`), so finished episodes
simply drop out.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from pipeline.model.skill_model import SkillModel
from pipeline.planning.cem import problem_generators
from pipeline.planning.costs import GoalCost
from pipeline.planning.skills import Plan, SkillPlanner, shift_plan


class SkillMPC:
    """Skill-sequence MPC for B environment slots.

    Args:
        model: The skill model (prior, TAWM, low-level policy).
        planner: The batched skill planner.
        sample_actions: Sample a ~ pi(a | s, z) instead of taking its mean.
        goal_dims: State dimensions the goal refers to (the environment spec's `goal_dims`);
            None: the first G (`GoalCost`'s default).
    """

    name = "oposm"

    def __init__(
        self,
        model: SkillModel,
        planner: SkillPlanner,
        sample_actions: bool = False,
        goal_dims: tuple[int, ...] | None = None,
    ):
        self.model = model
        self.planner = planner
        self.sample_actions = sample_actions
        self.goal_dims = goal_dims
        self.device = planner.device
        self._generators: list[torch.Generator] = []
        self._action_rngs: list[np.random.Generator] = []
        self._goals = torch.zeros(0)  # [B, G] goal per slot
        self._eps: torch.Tensor | None = None  # [B, L, z] last plan per slot (warm start)
        self._z: torch.Tensor | None = None  # [B, z] skill being executed per slot
        self._warm = torch.zeros(0, dtype=torch.bool)  # [B] slot has a plan to warm-start from

    def reset(self, goals: np.ndarray, seeds: Sequence[int]) -> None:
        """Start new episodes in all B slots: goals `[B, G]`, one seed per episode."""
        b = len(seeds)
        seq = [np.random.SeedSequence(int(s)).generate_state(2) for s in seeds]
        self._generators = problem_generators([int(s[0]) for s in seq], self.device)
        self._action_rngs = [np.random.default_rng(int(s[1])) for s in seq]
        self._goals = torch.as_tensor(goals, dtype=torch.float32, device=self.device)
        self._eps = self.planner.initial_mean(b)
        self._z = torch.zeros(b, self.model.config.z_dim, device=self.device)
        self._warm = torch.zeros(b, dtype=torch.bool, device=self.device)

    def replan(self, rows: np.ndarray, states: np.ndarray) -> Plan:
        """Plan for slots `rows [A]` from their states `[A, sd]`; their next skill is the plan's
        first. Returns the plan (on the agent's device)."""
        idx = torch.as_tensor(rows, dtype=torch.long, device=self.device)
        s0 = torch.as_tensor(states, dtype=torch.float32, device=self.device)
        init = None
        if self.planner.config.warm_start:
            warm = self._warm[idx, None, None]
            init = torch.where(warm, shift_plan(self._eps[idx]), torch.zeros_like(self._eps[idx]))
        plan = self.planner.plan(
            s0,
            GoalCost(self._goals[idx], self.goal_dims),
            [self._generators[i] for i in rows.tolist()],
            init,
        )
        self._eps[idx] = plan.eps
        self._z[idx] = plan.z[:, 0]
        self._warm[idx] = True
        return plan

    @torch.no_grad()
    def act(self, rows: np.ndarray, states: np.ndarray) -> np.ndarray:
        """Actions `[A, ad]` (raw units, float64) of the current skill for slots `rows [A]`."""
        s = torch.as_tensor(states, dtype=torch.float32, device=self.device)
        z = self._z[torch.as_tensor(rows, dtype=torch.long, device=self.device)]
        if not self.sample_actions:
            return self.model.act(s, z).double().cpu().numpy()
        dist = self.model.policy_dist(self.model.norm_states(s), z)
        mean, std = dist.mean.double().cpu().numpy(), dist.stddev.double().cpu().numpy()
        noise = np.stack([self._action_rngs[i].standard_normal(mean.shape[1]) for i in rows])
        a_norm = mean + std * noise
        m = self.model
        return a_norm * m.action_std.double().cpu().numpy() + m.action_mean.double().cpu().numpy()
