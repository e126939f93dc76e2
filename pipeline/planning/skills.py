"""Skill-sequence planning with the temporally abstract world model (paper §3, appendix C.6).

A plan is L vectors epsilon in the whitened skill space; skill i is
`z_i = mu_omega(s_i) + sigma_omega(s_i) * eps_i` (the skill prior at the state where it starts) and
the state it leads to is the TAWM mean `s_{i+1} = mu_psi(s_i, z_i)`. CEM searches epsilon-space,
where reasonable plans lie in a unit ball around the origin (the demonstrator's skills) whatever the
state. All K candidates of all B problems go through the model together: one prior and one TAWM
pass per skill step. Inside the search everything stays in the networks' normalized units (states
are mapped to raw units once per rollout, for the task cost); the prior at s_0 is computed once
for all K candidates; the networks run as `PlannerNets` (fused heads, in-place ReLUs, the TAWM's
mean network only); the best plan's states, skills and task cost are kept from the search, not
rolled out again.

`PlannerConfig.compile` runs each CEM iteration through `torch.compile`; on CUDA the whole plan is
also captured as one CUDA graph per (padded) batch size and replayed (fixed shapes, no host
synchronization inside a plan: see `pipeline.planning.cem`). Both give the eager plans up to
floating-point reassociation (tests/test_planning.py, tests/test_gpu.py).

Optionally the objective adds `prior_weight * mean(eps^2)`, the whitened skills' negative log-prior
up to constants (MAP-style planning). The paper plans on the task cost alone (§3); with a small,
briefly trained TAWM (this repository's CPU defaults) CEM otherwise finds unlikely skills whose
predicted end states are wrong (e.g. through walls), and the penalty keeps plans where the model
was trained (measured: `deploy.planner.prior_weight` in docs/findings.md).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from pipeline.model.skill_model import SkillModel
from pipeline.planning.cem import CEM, CEMConfig, CEMResult, CEMState
from pipeline.planning.costs import GoalCost
from pipeline.planning.fused import PlannerNets
from pipeline.planning.support import SkillSupport

if TYPE_CHECKING:  # imported where used: Triton is a Linux-only dependency
    from pipeline.planning.triton_rollout import TritonNets

# `predicted states [B, K, L + 1, sd] -> cost [B, K]`, e.g. `GoalCost`.
StateCost = Callable[[torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class PlannerConfig:
    """Skill planner settings (paper table 14: L = 10, K = 100, N_keep = 50, N_iters = 100). No
    defaults: `deploy.planner` (`pipeline.config.PlannerParams`) holds them, and
    `pipeline.planning.settings.planner_config` builds this from it.

    Attributes:
        horizon: Skills per plan [L].
        cem: Population, elites, iterations, std floor and early-stop cost of the CEM.
        init_std: Std of the initial epsilon Gaussian (1: the demonstrator's skill distribution).
        prior_weight: Weight of the skill-prior penalty mean(eps^2) in the objective (0: paper).
        skill_penalty: Goal units the MPC agent's `GoalCost` adds per skill before the nearest
            predicted state (0: the paper's cost; `GoalCost`).
        fall_penalty: Goal units the MPC agent's `GoalCost` adds to a plan predicted to fall
            (agents that can fall: the ant; 0: the paper's cost).
        uncertainty_weight: Weight of the plan's uncertainty in the objective: the TAWM's
            predicted std of each skill's outcome (normalized units, mean over the state's
            dims), summed over the skills (0: the paper's cost).
        support_weight: Weight of the plan's support excess in the objective: how much further
            each (start state, skill) pair of the plan is from the data's pairs than most of
            the data's own, summed over the skills (`pipeline.planning.support`; 0: the paper's
            cost). Needs the planner's `support` bank.
        data_skills: The first skill of every candidate is the nearest of the posterior skills
            of the `data_skills` bank windows whose first states are nearest the current state
            (CEM searches the rest as before); 0: any skill (the paper). Needs `support`.
        warm_start: Start each replan from the previous plan shifted by one skill (zeros appended)
            instead of from zeros.
        compile: Run CEM iterations through `torch.compile` (and, on CUDA, replay each plan as a
            CUDA graph); the same plans as eager up to floating-point rounding.
        dtype: What the prior and TAWM multiply in inside the search ("float32", or "bfloat16":
            about twice the matmul speed where the hardware has it; states stay float32).
        kernel: What computes the rollout and the goal cost: "torch" (one operation per layer and
            skill), or "triton": one Triton kernel per CEM iteration for a `GoalCost` without a
            fall test (`pipeline.planning.triton_rollout`; GPU; others stay on "torch").
    """

    horizon: int
    cem: CEMConfig
    init_std: float
    prior_weight: float
    skill_penalty: float
    fall_penalty: float
    uncertainty_weight: float
    warm_start: bool
    compile: bool
    dtype: str
    kernel: str
    support_weight: float
    data_skills: int

    def __post_init__(self) -> None:
        if self.kernel not in ("torch", "triton"):
            raise ValueError(f"kernel must be 'torch' or 'triton', got {self.kernel!r}")
        if self.uncertainty_weight < 0:
            raise ValueError(f"uncertainty_weight must be >= 0, got {self.uncertainty_weight}")
        if self.support_weight < 0:
            raise ValueError(f"support_weight must be >= 0, got {self.support_weight}")


@dataclass
class Plan:
    """The best skill sequence per problem and what the TAWM predicts for it.

    Attributes:
        eps: `[B, L, z]` whitened skills.
        z: `[B, L, z]` skills (z_0 is the one to execute now).
        states: `[B, L + 1, sd]` predicted states, states[:, 0] = s_0 (paper fig. 10, green dots).
        cost: `[B]` the plan's predicted task cost (without the prior penalty).
        objective: `[B]` what CEM minimized: task cost + prior penalty.
        iterations: `[B]` CEM iterations run.
    """

    eps: torch.Tensor
    z: torch.Tensor
    states: torch.Tensor
    cost: torch.Tensor
    objective: torch.Tensor
    iterations: torch.Tensor


class SkillPlanner:
    """CEM in epsilon-space over the TAWM's predictions, for B problems at once.

    Args:
        model: The skill model (prior and TAWM).
        config: The planner's settings.
        support: The data's (state, skill) pairs, for `config.support_weight` (needed then).
    """

    def __init__(
        self, model: SkillModel, config: PlannerConfig, support: SkillSupport | None = None
    ):
        if (config.support_weight or config.data_skills) and support is None:
            raise ValueError("support_weight and data_skills need the data's pairs: support")
        self.model = model
        self.config = config
        self.support = support
        self.cem = CEM(config.cem)
        self._compiled_step: Callable | None = None
        self._graphs: dict[int, _GraphedPlan] = {}

    @property
    def device(self) -> torch.device:
        return self.model.state_mean.device

    def initial_mean(self, batch: int) -> torch.Tensor:
        """`[B, L, z]` zeros: the prior's mean skills."""
        return torch.zeros(batch, self.config.horizon, self.model.config.z_dim, device=self.device)

    @torch.no_grad()
    def plan(
        self,
        s0: torch.Tensor,
        cost: StateCost,
        keys: torch.Tensor,
        init_mean: torch.Tensor | None = None,
    ) -> Plan:
        """Plan from the start states `s0 [B, sd]` of B problems.

        Args:
            s0: `[B, sd]` current states (raw units).
            cost: Task cost of predicted states `[B, K, L + 1, sd]` -> `[B, K]`.
            keys: `[B]` int64 random-stream keys, one per problem (`noise.problem_keys`).
            init_mean: `[B, L, z]` initial epsilon means (warm start); zeros if None.
        """
        mean = self.initial_mean(len(s0)) if init_mean is None else init_mean
        if self.config.compile and s0.device.type == "cuda":
            if not isinstance(cost, GoalCost):
                raise ValueError("CUDA-graph planning takes a GoalCost (its goals are captured)")
            result = self._graphed(len(s0)).run(s0, cost, keys, mean)
        else:
            result = self._search(s0, cost, keys, mean)
        states, z, task = result.extras
        return Plan(result.best, z, states, task, result.cost, result.iterations)

    def _search(
        self, s0: torch.Tensor, cost: StateCost, keys: torch.Tensor, mean: torch.Tensor
    ) -> CEMResult:
        """The CEM search (eager, or with compiled iterations); extras: states, z, task cost."""
        dtype = getattr(torch, self.config.dtype)
        nets = PlannerNets(self.model, dtype)
        if self._fused(cost):
            from pipeline.planning.triton_rollout import TritonNets

            fused = TritonNets(self.model, dtype)
            goal = fused.goal_inputs(cost.goals, cost.dims)  # once per plan
            nets = FusedNets(nets, fused, goal, cost.skill_penalty)
        s0_n = self.model.norm_states(s0)
        prior0 = nets.prior(s0_n)  # once for all K candidates
        local = None  # the data's skills near s_0, for the first skill (`data_skills`)
        if self.config.data_skills:
            local = self.support.local_skills(s0_n, self.config.data_skills)
        if not self.config.compile:
            return self.cem.minimize(
                lambda eps: self._objective(eps, nets, s0, s0_n, prior0, cost, local),
                mean,
                self.config.init_std,
                keys,
            )
        if self._compiled_step is None:
            # Dynamic batch from the start: one graph for every batch size above 1 (deploy's
            # batches shrink as episodes end), not one per size up to dynamo's recompile limit.
            self._compiled_step = torch.compile(self._step, dynamic=True)
        compiled = self._compiled_step

        def step(state: CEMState, _, iteration_keys: torch.Tensor) -> CEMState:
            # The first iteration (no best yet: another graph) runs eagerly.
            run = self._step if state.best_extras is None else compiled
            return run(state, iteration_keys, nets, s0, s0_n, prior0, cost, local)

        return self.cem.minimize(None, mean, self.config.init_std, keys, step=step)

    def _fused(self, cost: StateCost) -> bool:
        """Whether the Triton kernel computes this plan's rollout and cost (`config.kernel`)."""
        model = self.model.config
        if self.config.kernel != "triton" or model.tawm_components > 1 or model.tawm_residual:
            return False
        if self.config.uncertainty_weight or self.config.support_weight or self.config.data_skills:
            return False  # the kernel chains the prior's skills and the TAWM's means only
        return isinstance(cost, GoalCost) and not cost.fall_penalty and cost.scale is None

    def _step(
        self,
        state: CEMState,
        keys: torch.Tensor,
        nets: PlannerNets | FusedNets,
        s0: torch.Tensor,
        s0_n: torch.Tensor,
        prior0: tuple[torch.Tensor, torch.Tensor],
        cost: StateCost,
        local: torch.Tensor | None = None,
    ) -> CEMState:
        """One CEM iteration with the objective built inside (what `torch.compile` takes)."""
        return self.cem.step(
            state, lambda eps: self._objective(eps, nets, s0, s0_n, prior0, cost, local), keys
        )

    def _objective(
        self,
        eps: torch.Tensor,
        nets: PlannerNets | FusedNets,
        s0: torch.Tensor,
        s0_n: torch.Tensor,
        prior0: tuple[torch.Tensor, torch.Tensor],
        cost: StateCost,
        local: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        """Objective `[B, K]` of candidates `eps [B, K, L, z]`, and their states, skills, task."""
        if isinstance(nets, FusedNets):  # one kernel: rollout and goal cost (`_fused`)
            states, z, task = nets.triton.rollout_cost(
                eps, s0, s0_n, prior0, nets.goal, nets.skill_penalty
            )
            uncertainty = None  # `_fused` leaves plans with an uncertainty weight to torch
        else:
            states, z, uncertainty = self._rollout(eps, nets, s0, s0_n, prior0, local)
            task = cost(states)
        weight = self.config.prior_weight
        objective = task + weight * eps.pow(2).mean(dim=(-2, -1)) if weight else task
        if uncertainty is not None:
            objective = objective + self.config.uncertainty_weight * uncertainty
        if self.config.support_weight:
            starts_n = self.model.norm_states(states[:, :, :-1])  # each skill's start state
            distance = self.support.excess(starts_n, z).sum(dim=-1)
            objective = objective + self.config.support_weight * distance
        return objective, (states, z, task)

    def _rollout(
        self,
        eps: torch.Tensor,
        nets: PlannerNets,
        s0: torch.Tensor,
        s0_n: torch.Tensor,
        prior0: tuple[torch.Tensor, torch.Tensor],
        local: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Chain prior and TAWM mean over `eps [B, K, L, z]` from `s0 [B, sd]` (raw; `s0_n`
        normalized, `prior0` its prior mean and std `[B, z]`): raw states `[B, K, L + 1, sd]`
        (s_0 first), skills `[B, K, L, z]` and, with `uncertainty_weight`, the plan's
        uncertainty `[B, K]` (the TAWM's std of each outcome, mean over dims, summed over the
        skills; else None). The same chain as `rollout_skills`."""
        m = self.model
        b, k, n_skills, z_dim = eps.shape
        sd = s0.shape[-1]
        flat = eps.reshape(b * k, n_skills, z_dim)  # rows: one matrix product per network
        s = s0_n[:, None].expand(b, k, sd).reshape(b * k, sd)
        skills, states = [], []
        weighted = self.config.uncertainty_weight > 0
        uncertainty = torch.zeros(b * k, device=s0.device) if weighted else None
        for i in range(n_skills):
            if i:
                mu, sigma = nets.prior(s)
                skills.append(torch.addcmul(mu, sigma, flat[:, i]))
            else:
                z0 = torch.addcmul(prior0[0][:, None], prior0[1][:, None], eps[:, :, 0])
                if local is not None:  # the nearest of the data's skills near s_0
                    z0 = self.support.snap(z0, local)
                skills.append(z0.reshape(b * k, z_dim))
            if uncertainty is None:
                s = nets.tawm_mean(s, skills[-1])
            else:
                s, std = nets.tawm_mean_std(s, skills[-1])
                uncertainty += std.mean(dim=-1)
            states.append(s)
        predicted = torch.stack(states, dim=1) * m.state_std + m.state_mean  # [BK, L, sd]
        start = s0[:, None, None].expand(b, k, 1, sd)
        return (
            torch.cat([start, predicted.view(b, k, n_skills, sd)], dim=2),
            torch.stack(skills, dim=1).view(b, k, n_skills, z_dim),
            None if uncertainty is None else uncertainty.view(b, k),
        )

    def _graphed(self, batch: int) -> _GraphedPlan:
        """The captured plan for `batch` problems (padded to a power of two: few graphs)."""
        size = 1 << max(batch - 1, 0).bit_length()
        if size not in self._graphs:
            self._graphs[size] = _GraphedPlan(self, size)
        return self._graphs[size]


class _GraphedPlan:
    """A whole plan of `size` problems captured as one CUDA graph (compiled CEM iterations, the
    goal cost); inputs are copied into static buffers, padding rows repeat problem 0."""

    def __init__(self, planner: SkillPlanner, size: int):
        m, cfg = planner.model, planner.config
        device = planner.device
        self.size = size
        self.s0 = torch.zeros(size, m.config.state_dim, device=device)
        self.mean = torch.zeros(size, cfg.horizon, m.config.z_dim, device=device)
        self.keys = torch.zeros(size, dtype=torch.long, device=device)
        self.goals: torch.Tensor | None = None
        self.planner = planner
        self.graph: torch.cuda.CUDAGraph | None = None
        self.out: CEMResult | None = None
        self.key: tuple | None = None  # the captured cost's dims and penalty

    def _capture(self, cost: GoalCost) -> None:
        self.goals = torch.zeros(self.size, cost.goals.shape[-1], device=self.s0.device)
        self.key = cost.key
        static_cost = cost.with_goals(self.goals)

        def search() -> CEMResult:
            return self.planner._search(self.s0, static_cost, self.keys, self.mean)

        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):  # warm-up (compilation, allocator) off the capture
            for _ in range(2):
                search()
        torch.cuda.current_stream().wait_stream(side)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self.out = search()

    def run(
        self, s0: torch.Tensor, cost: GoalCost, keys: torch.Tensor, mean: torch.Tensor
    ) -> CEMResult:
        """Copy the inputs in, replay, copy the first `len(s0)` rows out."""
        b = len(s0)
        if self.graph is None or self.key != cost.key:
            self._capture(cost)
        pad = self.size - b
        for static, value in ((self.s0, s0), (self.goals, cost.goals), (self.keys, keys),
                              (self.mean, mean)):  # fmt: skip
            static[:b].copy_(value)
            if pad:
                static[b:].copy_(value[:1].expand(pad, *value.shape[1:]))
        self.graph.replay()
        out = self.out
        return CEMResult(
            out.best[:b].clone(), out.cost[:b].clone(), out.mean[:b].clone(), out.std[:b].clone(),
            out.iterations[:b].clone(), tuple(e[:b].clone() for e in out.extras),
        )  # fmt: skip


@dataclass
class FusedNets:
    """`PlannerNets` for the prior at s_0, `TritonNets` for the rollout and its goal cost
    (`goal`: the plan's goals as the kernel reads them, `TritonNets.goal_inputs`)."""

    torch_nets: PlannerNets
    triton: TritonNets
    goal: tuple[torch.Tensor, torch.Tensor]
    skill_penalty: float

    def prior(self, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.torch_nets.prior(s)


def shift_plan(eps: torch.Tensor) -> torch.Tensor:
    """Warm start after executing skill 0: `[B, L, z]` -> `[eps_1, ..., eps_{L-1}, 0]`."""
    return torch.cat([eps[:, 1:], torch.zeros_like(eps[:, :1])], dim=1)
