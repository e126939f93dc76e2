"""Model-predictive control with skills (paper §3): plan, execute the first skill for tau steps with
the low-level policy, replan from the state reached.

The agent drives a batch of environment slots. Each slot has its own random streams (CEM noise and
action noise: counter-based, keyed by the episode's seed and the replan or step number), so what
happens in one episode does not depend on the others sharing the batch. `replan` and `act` take
the slots to serve (`rows`), so finished episodes simply drop out. Everything stays on the
model's device; `act` copies its actions to the host once per environment step.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from pipeline.model.skill_model import SkillModel
from pipeline.planning.costs import GoalCost, ValueGoalCost
from pipeline.planning.noise import normal, problem_keys, substream
from pipeline.planning.skills import Plan, SkillPlanner, shift_plan
from pipeline.planning.subgoals import StuckWatch, SubgoalGraph
from pipeline.planning.subtasks import ObjectSubtasks

# `(states [..., sd], goals [..., G]) -> [...]` steps to the goal (a learned value's).
StepsToGo = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


class SkillMPC:
    """Skill-sequence MPC for B environment slots.

    Args:
        model: The skill model (prior, TAWM, low-level policy).
        planner: The batched skill planner.
        sample_actions: Sample a ~ pi(a | s, z) instead of its mean (`deploy.sample_actions`).
        goal_dims: State dimensions the goal refers to (the environment spec's `goal_dims`);
            None: the first G (`GoalCost`'s default).
        subgoals: Plan to its waypoints instead of the goal when the goal is far
            (`deploy.subgoals`); None: always to the goal (the paper).
        fallen: Test of predicted states for a fallen agent (the environment spec's `fallen`,
            the ant), for the planner's `fall_penalty`; None: the agent cannot fall.
        goal_scale: Per goal dim, what the goal cost divides its distance by (the environment
            spec's `goal_scale`: OGBench manipulation's success tolerances); None: raw units.
        value: A learned steps-to-go `(states, goals) -> steps`, its weight and the skill length
            T, for `ValueGoalCost` (`value.weight`); None: the paper's `GoalCost`.
        subtasks: Plan to one object of the goal at a time (`deploy.object_subtasks`); None:
            to the whole goal (the paper).
        stuck: With `subgoals`: plan to the goal until this says an episode is stuck, then to
            the waypoints (`deploy.subgoals.patience`); None: waypoints from the first replan.
    """

    name = "oposm"

    def __init__(
        self,
        model: SkillModel,
        planner: SkillPlanner,
        sample_actions: bool,
        goal_dims: tuple[int, ...] | None = None,
        subgoals: SubgoalGraph | None = None,
        fallen: Callable[[torch.Tensor], torch.Tensor] | None = None,
        goal_scale: Sequence[float] | None = None,
        value: tuple[StepsToGo, float, int] | None = None,
        subtasks: ObjectSubtasks | None = None,
        stuck: StuckWatch | None = None,
    ):
        if subgoals is not None and subtasks is not None:
            raise ValueError("plan to waypoints (subgoals) or to one object at a time, not both")
        if stuck is not None and subgoals is None:
            raise ValueError("a stuck watch switches to subgoals' waypoints: give it subgoals")
        self.model = model
        self.stuck = stuck
        self.subtasks = subtasks
        self.value = value
        self.goal_scale = goal_scale
        self.fallen = fallen
        self.subgoals = subgoals
        self.targets: torch.Tensor | None = None  # [A, G] the last replan's waypoints, if any
        self.planner = planner
        self.sample_actions = sample_actions
        self.goal_dims = goal_dims
        self.device = planner.device
        self._plan_keys = torch.zeros(0, dtype=torch.long)  # [B] CEM-noise stream per slot
        self._action_keys = torch.zeros(0, dtype=torch.long)  # [B] action-noise stream per slot
        self._replans = torch.zeros(0, dtype=torch.long)  # [B] replans so far per slot
        self._steps = torch.zeros(0, dtype=torch.long)  # [B] actions taken so far per slot
        self._goals = torch.zeros(0)  # [B, G] goal per slot
        self._eps: torch.Tensor | None = None  # [B, L, z] last plan per slot (warm start)
        self._z: torch.Tensor | None = None  # [B, z] skill being executed per slot
        self._warm = torch.zeros(0, dtype=torch.bool)  # [B] slot has a plan to warm-start from

    def reset(self, goals: np.ndarray, seeds: Sequence[int]) -> None:
        """Start new episodes in all B slots: goals `[B, G]`, one seed per episode."""
        b = len(seeds)
        seq = [np.random.SeedSequence(int(s)).generate_state(2) for s in seeds]
        self._plan_keys = problem_keys([int(s[0]) for s in seq], self.device)
        self._action_keys = problem_keys([int(s[1]) for s in seq], self.device)
        self._replans = torch.zeros(b, dtype=torch.long, device=self.device)
        self._steps = torch.zeros(b, dtype=torch.long, device=self.device)
        self._goals = torch.as_tensor(goals, dtype=torch.float32, device=self.device)
        self._eps = self.planner.initial_mean(b)
        self._z = torch.zeros(b, self.model.config.z_dim, device=self.device)
        self._warm = torch.zeros(b, dtype=torch.bool, device=self.device)
        if self.stuck is not None:
            self.stuck.reset(b, self.device)

    def replan(self, rows: np.ndarray, states: np.ndarray) -> Plan:
        """Plan for slots `rows [A]` from their states `[A, sd]`; their next skill is the plan's
        first. Returns the plan (on the agent's device)."""
        idx = torch.as_tensor(rows, dtype=torch.long, device=self.device)
        s0 = torch.as_tensor(states, dtype=torch.float32, device=self.device)
        init = None
        if self.planner.config.warm_start:
            warm = self._warm[idx, None, None]
            init = torch.where(warm, shift_plan(self._eps[idx]), torch.zeros_like(self._eps[idx]))
        targets, cfg = self._goals[idx], self.planner.config
        if self.subgoals is not None:
            dims = list(self.goal_dims or range(targets.shape[-1]))
            waypoints = self.subgoals.waypoints(s0[:, dims], targets)
            if self.stuck is not None:  # the goal itself until the episode is stuck
                far = (s0[:, dims] - targets).norm(dim=-1)
                waypoints = torch.where(self.stuck.update(idx, far)[:, None], waypoints, targets)
            targets = waypoints
            self.targets = targets
        if self.subtasks is not None:
            dims = list(self.goal_dims or range(targets.shape[-1]))
            targets = self.subtasks.targets(s0[:, dims], targets)
        if self.value is None:
            cost = GoalCost(
                targets, self.goal_dims, cfg.skill_penalty, cfg.fall_penalty, self.fallen,
                self.goal_scale,
            )  # fmt: skip
        else:
            steps_to_go, weight, skill_steps = self.value
            cost = ValueGoalCost(
                targets, steps_to_go, weight, skill_steps, self.goal_dims, cfg.skill_penalty,
                self.goal_scale,
            )  # fmt: skip
        plan = self.planner.plan(
            s0,
            cost,
            substream(self._plan_keys[idx], self._replans[idx]),
            init,
        )
        self._replans[idx] += 1
        self._eps[idx] = plan.eps
        self._z[idx] = plan.z[:, 0]
        self._warm[idx] = True
        return plan

    @torch.no_grad()
    def act(self, rows: np.ndarray, states: np.ndarray) -> np.ndarray:
        """Actions `[A, ad]` (raw units, float64) of the current skill for slots `rows [A]`."""
        m = self.model
        idx = torch.as_tensor(rows, dtype=torch.long, device=self.device)
        s = torch.as_tensor(states, dtype=torch.float32, device=self.device)
        mean, std = m.policy_stats(m.norm_states(s), self._z[idx])
        if self.sample_actions:
            keys = substream(self._action_keys[idx], self._steps[idx])
            mean = mean + std * normal(keys, mean.shape[1:])
            self._steps[idx] += 1
        return m.clip_actions(mean * m.action_std + m.action_mean).double().cpu().numpy()
