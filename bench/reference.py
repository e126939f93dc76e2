"""THE REFERENCE for `oposm bench plan`: a plain eager implementation of the paper's planning
procedure (appendix C.6), written as the paper's code does it, so the batched planner is compared
with what it replaces in the same process, on the same model and settings.

One environment at a time. Each CEM iteration draws K whitened skill sequences from one
`torch.Generator`, chains them through the skill prior and the TAWM in raw units with the model's
public methods (`skill_prior`, `predict_end`: normalize, both heads, de-normalize, per skill step),
scores them by the goal distance of the nearest predicted state (+ the prior penalty), sorts them
and refits the Gaussian to the elites. Not used by the pipeline; benchmarks only.
"""

from __future__ import annotations

import torch

from pipeline.model.skill_model import SkillModel
from pipeline.planning.skills import PlannerConfig


class ReferencePlanner:
    """The paper's procedure, one environment per call (see the module docstring)."""

    def __init__(self, model: SkillModel, config: PlannerConfig):
        self.model = model
        self.config = config

    @torch.no_grad()
    def plan_one(
        self, s0: torch.Tensor, goal: torch.Tensor, generator: torch.Generator
    ) -> tuple[torch.Tensor, float]:
        """Best whitened skills `[L, z]` and their objective from raw `s0 [sd]` to `goal [G]`."""
        cfg, cem, m = self.config, self.config.cem, self.model
        shape = (cfg.horizon, m.config.z_dim)
        mean = torch.zeros(shape, device=s0.device)
        std = torch.full(shape, cfg.init_std, device=s0.device)
        best, best_cost = mean.clone(), float("inf")
        for _ in range(cem.iterations):
            eps = mean + std * torch.randn(
                (cem.candidates, *shape), generator=generator, device=s0.device
            )
            s = s0.expand(cem.candidates, -1)
            distances = []
            for i in range(cfg.horizon):
                mu, sigma = m.skill_prior(s)
                s = m.predict_end(s, mu + sigma * eps[:, i])[0]
                distances.append(torch.linalg.vector_norm(s[:, : len(goal)] - goal, dim=-1))
            cost = torch.stack(distances, dim=1).amin(dim=1)
            cost = cost + cfg.prior_weight * eps.pow(2).mean(dim=(1, 2))
            order = torch.argsort(cost)
            if cost[order[0]] < best_cost:
                best, best_cost = eps[order[0]].clone(), float(cost[order[0]])
            elites = eps[order[: cem.elites]]
            mean, std = elites.mean(dim=0), elites.std(dim=0, correction=0).clamp_min(cem.min_std)
        return best, best_cost

    def plan(self, s0: torch.Tensor, goals: torch.Tensor, seed: int) -> list[float]:
        """Plan for B environments one after the other (`s0 [B, sd]`, `goals [B, G]`)."""
        out = []
        for b in range(len(s0)):
            generator = torch.Generator(device=s0.device).manual_seed(seed + b)
            out.append(self.plan_one(s0[b], goals[b], generator)[1])
        return out
