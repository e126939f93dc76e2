"""Low-level planning (LLP), the paper's single-step baseline (§4.2, table 4, appendix D).

A plan is L whitened actions epsilon; along the single-step model's predicted mean states,

    a_t = mu_BC(s_t) + sigma_BC(s_t) * eps_t,     s_{t+1} = mean of p(s' | s_t, a_t),

with p(a | s) the Gaussian BC policy (the paper code's `Prior` over actions) and p(s' | s, a) the
single-step dynamics model. The same CEM as the skill planner searches epsilon-space (the unit ball
around the demonstrator's actions); the cost is the task cost of the predicted states plus
`l2_penalty * mean(eps^2)`, as in the paper code (`cem_l2_pen`). The agent executes the first
`execute` actions of the plan as they were computed along the predicted states (open loop, as the
paper code's `convert_epsilon_to_a`), then replans from the state reached.

The paper code's maze2d settings: L 20, execute 5, K 100, keep 20 %, 5 iterations, l2 0.01, no
warm start, CEM's final mean executed (not its best sample).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.model.dynamics import DynamicsModel
from pipeline.model.policy import GaussianPolicy
from pipeline.planning.cem import CEM, CEMConfig
from pipeline.planning.costs import GoalCost
from pipeline.planning.noise import problem_keys, substream
from pipeline.planning.skills import StateCost


@dataclass(frozen=True)
class LLPConfig:
    """Low-level planner settings (the paper code's names in brackets). No defaults: `deploy.llp`
    (`pipeline.config.LLPParams`) holds them, and `pipeline.planning.settings.llp_config` builds
    this from it.

    Attributes:
        horizon: Actions per plan [action_seq_len].
        execute: Actions executed per replan [H].
        cem: Population [batch_size], elites [keep_frac * K], iterations [n_iters], std floor,
            early-stop cost.
        init_std: Std of the initial epsilon Gaussian (1: the BC policy's action distribution).
        l2_penalty: Weight of mean(eps^2) in the objective [cem_l2_pen].
        plan_from: `mean`: execute CEM's final mean (the paper code); `best`: its best sample.
        warm_start: Start each replan from the previous plan shifted by `execute` actions.
    """

    horizon: int
    execute: int
    cem: CEMConfig
    init_std: float
    l2_penalty: float
    plan_from: str
    warm_start: bool

    def __post_init__(self) -> None:
        if not 1 <= self.execute <= self.horizon:
            raise ValueError(f"execute must be in [1, horizon={self.horizon}], got {self.execute}")
        if self.plan_from not in ("mean", "best"):
            raise ValueError(f"plan_from must be 'mean' or 'best', got {self.plan_from!r}")


@dataclass
class ActionPlan:
    """The chosen action sequence per problem and the single-step model's predicted path.

    Attributes:
        eps: `[B, L, ad]` whitened actions.
        actions: `[B, L, ad]` raw actions computed along the predicted states.
        states: `[B, L + 1, sd]` predicted states, states[:, 0] = s_0 (paper fig. 10, pink).
        cost: `[B]` the plan's predicted task cost (without the penalty).
        objective: `[B]` the best objective CEM saw (task cost + penalty).
        iterations: `[B]` CEM iterations run.
    """

    eps: torch.Tensor
    actions: torch.Tensor
    states: torch.Tensor
    cost: torch.Tensor
    objective: torch.Tensor
    iterations: torch.Tensor


class LowLevelPlanner:
    """CEM in whitened action space over the single-step model's predictions, for B problems."""

    def __init__(self, policy: GaussianPolicy, dynamics: DynamicsModel, config: LLPConfig):
        if policy.goal_conditioned:
            raise ValueError("LLP's action prior is p(a | s); got a goal-conditioned policy")
        self.policy = policy
        self.dynamics = dynamics
        self.config = config
        self.cem = CEM(config.cem)

    @property
    def device(self) -> torch.device:
        return self.policy.state_mean.device

    def initial_mean(self, batch: int) -> torch.Tensor:
        """`[B, L, ad]` zeros: the BC policy's mean actions."""
        ad = self.policy.config.action_dim
        return torch.zeros(batch, self.config.horizon, ad, device=self.device)

    @torch.no_grad()
    def rollout(self, s0: torch.Tensor, eps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Whitened actions along the predicted mean states.

        Args:
            s0: `[*B, sd]` raw start states (broadcast to the batch shape of `eps`).
            eps: `[*B, L, ad]` whitened actions.

        Returns:
            Raw actions `[*B, L, ad]` and states `[*B, L + 1, sd]` (s_0 first).
        """
        *batch, steps, ad = eps.shape
        sd = s0.shape[-1]
        s = s0.expand(*batch, sd).reshape(-1, sd)
        flat = eps.reshape(-1, steps, ad)
        states, actions = [s], []
        for t in range(steps):
            mean, std = self.policy.action_stats(s)
            actions.append(mean + std * flat[:, t])
            s = self.dynamics.predict(s, actions[-1])[0]
            states.append(s)
        return (
            torch.stack(actions, dim=1).reshape(*batch, steps, ad),
            torch.stack(states, dim=1).reshape(*batch, steps + 1, sd),
        )

    def plan(
        self,
        s0: torch.Tensor,
        cost: StateCost,
        keys: torch.Tensor,
        init_mean: torch.Tensor | None = None,
    ) -> ActionPlan:
        """Plan from the start states `s0 [B, sd]` of B problems.

        Args:
            s0: `[B, sd]` current states (raw units).
            cost: Task cost of predicted states `[B, K, L + 1, sd]` -> `[B, K]`.
            keys: `[B]` int64 random-stream keys, one per problem (`noise.problem_keys`).
            init_mean: `[B, L, ad]` initial epsilon means (warm start); zeros if None.
        """
        mean = self.initial_mean(len(s0)) if init_mean is None else init_mean
        weight = self.config.l2_penalty

        def objective(eps: torch.Tensor) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
            actions, states = self.rollout(s0[:, None], eps)  # [B, K, L + 1, sd]
            task = cost(states)
            penalized = task + weight * eps.pow(2).mean(dim=(-2, -1)) if weight else task
            return penalized, (actions, states, task)

        result = self.cem.minimize(objective, mean, self.config.init_std, keys)
        if self.config.plan_from == "best":  # its path was computed in the search
            eps, (actions, states, task_cost) = result.best, result.extras
        else:  # CEM's final mean was never evaluated: roll it out
            eps = result.mean
            actions, states = (x[:, 0] for x in self.rollout(s0[:, None], eps[:, None]))
            task_cost = cost(states[:, None])[:, 0]
        return ActionPlan(eps, actions, states, task_cost, result.cost, result.iterations)


class LowLevelMPC:
    """LLP as an agent for B environment slots: plan, execute `execute` planned actions, replan.

    Each slot draws its CEM noise from its own counter-based stream, keyed by the episode seed and
    the replan number (results do not depend on the other episodes sharing the batch).

    Args:
        planner: The batched low-level planner.
        goal_dims: State dimensions the goal refers to (None: the first G).
        goal_scale: Per goal dim, what the goal cost divides its distance by (`GoalCost`);
            None: raw units.
    """

    name = "llp"

    def __init__(
        self,
        planner: LowLevelPlanner,
        goal_dims: tuple[int, ...] | None = None,
        goal_scale: Sequence[float] | None = None,
    ):
        self.planner = planner
        self.goal_dims = goal_dims
        self.goal_scale = goal_scale
        self.device = planner.device
        self._keys = torch.zeros(0, dtype=torch.long)  # [B] random-stream key per slot
        self._replans = torch.zeros(0, dtype=torch.long)  # [B] replans so far per slot
        self._goals = torch.zeros(0)
        self._eps: torch.Tensor | None = None  # [B, L, ad] last plan per slot (warm start)
        self._actions = np.zeros((0, 0, 0))  # [B, L, ad] planned raw actions per slot
        self._next = np.zeros(0, dtype=np.int64)  # [B] index of the next planned action
        self._warm = torch.zeros(0, dtype=torch.bool)

    def reset(self, goals: np.ndarray, seeds: Sequence[int]) -> None:
        """Start new episodes in all B slots: goals `[B, G]`, one seed per episode."""
        b = len(seeds)
        seq = [np.random.SeedSequence(int(s)).generate_state(1) for s in seeds]
        self._keys = problem_keys([int(s[0]) for s in seq], self.device)
        self._replans = torch.zeros(b, dtype=torch.long, device=self.device)
        self._goals = torch.as_tensor(goals, dtype=torch.float32, device=self.device)
        self._eps = self.planner.initial_mean(b)
        ad = self.planner.policy.config.action_dim
        self._actions = np.zeros((b, self.planner.config.horizon, ad))
        self._next = np.zeros(b, dtype=np.int64)
        self._warm = torch.zeros(b, dtype=torch.bool, device=self.device)

    def replan(self, rows: np.ndarray, states: np.ndarray) -> ActionPlan:
        """Plan for slots `rows [A]` from their states `[A, sd]`; their next actions are the
        plan's first ones."""
        idx = torch.as_tensor(rows, dtype=torch.long, device=self.device)
        s0 = torch.as_tensor(states, dtype=torch.float32, device=self.device)
        init = None
        if self.planner.config.warm_start:
            k = self.planner.config.execute
            prev = self._eps[idx]
            shifted = torch.cat([prev[:, k:], torch.zeros_like(prev[:, :k])], dim=1)
            init = torch.where(self._warm[idx, None, None], shifted, torch.zeros_like(prev))
        plan = self.planner.plan(
            s0,
            GoalCost(self._goals[idx], self.goal_dims, scale=self.goal_scale),
            substream(self._keys[idx], self._replans[idx]),
            init,
        )
        self._replans[idx] += 1
        self._eps[idx] = plan.eps
        self._warm[idx] = True
        self._actions[rows] = plan.actions.double().cpu().numpy()
        self._next[rows] = 0
        return plan

    def act(self, rows: np.ndarray, states: np.ndarray) -> np.ndarray:
        """The next planned actions `[A, ad]` (raw units, float64) of slots `rows [A]`."""
        k = np.minimum(self._next[rows], self._actions.shape[1] - 1)
        self._next[rows] += 1
        return self._actions[rows, k]
