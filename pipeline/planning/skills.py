"""Skill-sequence planning with the temporally abstract world model (paper §3, appendix C.6).

A plan is L vectors epsilon in the whitened skill space; skill i is
`z_i = mu_omega(s_i) + sigma_omega(s_i) * eps_i` (the skill prior at the state where it starts) and
the state it leads to is the TAWM mean `s_{i+1} = mu_psi(s_i, z_i)`. CEM searches epsilon-space,
where reasonable plans lie in a unit ball around the origin (the demonstrator's skills) whatever the
state. All K candidates of all B problems go through the model together: one prior and one TAWM
pass per skill step.

Optionally the objective adds `prior_weight * mean(eps^2)`, the whitened skills' negative log-prior
up to constants (MAP-style planning). The paper plans on the task cost alone (§3); with a small,
briefly trained TAWM (this repository's CPU defaults) CEM otherwise finds unlikely skills whose
predicted end states are wrong (e.g. through walls), and the penalty keeps plans where the model
was trained (measured: `deploy.planner.prior_weight` in the README).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch

from pipeline.model.rollout import rollout_skills
from pipeline.model.skill_model import SkillModel
from pipeline.planning.cem import CEM, CEMConfig

# `(predicted states [A, K, L + 1, sd], rows [A]) -> cost [A, K]`, e.g. `GoalCost`.
StateCost = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class PlannerConfig:
    """Skill planner settings (paper table 14: L = 10, K = 100, N_keep = 50, N_iters = 100).

    Attributes:
        horizon: Skills per plan [L].
        cem: Population, elites, iterations, std floor and early-stop cost of the CEM.
        init_std: Std of the initial epsilon Gaussian (1: the demonstrator's skill distribution).
        prior_weight: Weight of the skill-prior penalty mean(eps^2) in the objective (0: paper).
        warm_start: Start each replan from the previous plan shifted by one skill (zeros appended)
            instead of from zeros.
    """

    horizon: int = 10
    cem: CEMConfig = field(default_factory=CEMConfig)
    init_std: float = 1.0
    prior_weight: float = 0.0
    warm_start: bool = True


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
    """CEM in epsilon-space over the TAWM's predictions, for B problems at once."""

    def __init__(self, model: SkillModel, config: PlannerConfig):
        self.model = model
        self.config = config
        self.cem = CEM(config.cem)

    @property
    def device(self) -> torch.device:
        return self.model.state_mean.device

    def initial_mean(self, batch: int) -> torch.Tensor:
        """`[B, L, z]` zeros: the prior's mean skills."""
        return torch.zeros(batch, self.config.horizon, self.model.config.z_dim, device=self.device)

    def plan(
        self,
        s0: torch.Tensor,
        cost: StateCost,
        generators: Sequence[torch.Generator],
        init_mean: torch.Tensor | None = None,
    ) -> Plan:
        """Plan from the start states `s0 [B, sd]` of B problems.

        Args:
            s0: `[B, sd]` current states (raw units).
            cost: Cost of predicted states `[A, K, L + 1, sd]` for problems `rows [A]`.
            generators: One generator per problem (on the model's device).
            init_mean: `[B, L, z]` initial epsilon means (warm start); zeros if None.
        """
        mean = self.initial_mean(len(s0)) if init_mean is None else init_mean
        weight = self.config.prior_weight

        def objective(eps: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
            states = rollout_skills(self.model, s0[rows, None], eps=eps).states  # [A, K, L+1, sd]
            task = cost(states, rows)
            return task + weight * eps.pow(2).mean(dim=(-2, -1)) if weight else task

        result = self.cem.minimize(objective, mean, self.config.init_std, generators)
        best = rollout_skills(self.model, s0[:, None], eps=result.best[:, None])  # K = 1
        task_cost = cost(best.states, torch.arange(len(s0), device=s0.device))[:, 0]
        return Plan(
            result.best, best.z[:, 0], best.states[:, 0], task_cost, result.cost, result.iterations
        )


def shift_plan(eps: torch.Tensor) -> torch.Tensor:
    """Warm start after executing skill 0: `[B, L, z]` -> `[eps_1, ..., eps_{L-1}, 0]`."""
    return torch.cat([eps[:, 1:], torch.zeros_like(eps[:, :1])], dim=1)
