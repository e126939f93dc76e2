"""A batched cross-entropy method (Rubinstein, 1999) that knows nothing about the world model.

`CEM.minimize` solves B independent problems at once. Each problem keeps a diagonal Gaussian over
a candidate of any shape; every iteration samples K candidates per problem, asks the cost function
for all of them in one call (`[A, K, *shape] -> [A, K]`, A = problems still running), and refits the
Gaussian to the N_keep cheapest (paper appendix C.6). The best candidate seen is returned.

Each problem draws its noise from its own `torch.Generator`, so a problem's result does not depend
on which other problems share the batch (tests/test_planning.py checks this). Problems whose best
cost falls under `stop_cost` stop early (the paper's threshold, §4.2 footnote 1) and no longer draw
noise or cost evaluations.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from pipeline.errors import UserError

# `(candidates [A, K, *shape], rows [A]) -> cost [A, K]`; `rows` index the problems of the batch
# that the A candidate sets belong to, so the cost can look up each problem's context.
CostFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class CEMConfig:
    """CEM settings (paper table 14 names in brackets).

    Attributes:
        population: Candidates sampled per problem and iteration [K].
        elites: Cheapest candidates the Gaussian is refit to [N_keep].
        iterations: Maximum iterations [N_iters].
        min_std: Floor on the refit std, so the search never collapses to a point.
        stop_cost: Stop a problem once its best cost is below this; None: run all iterations.
    """

    population: int = 100
    elites: int = 50
    iterations: int = 100
    min_std: float = 0.0
    stop_cost: float | None = None

    def __post_init__(self) -> None:
        if self.population < 1 or self.iterations < 1:
            raise UserError(
                f"CEM needs population >= 1 and iterations >= 1, got {self.population}, "
                f"{self.iterations}"
            )
        if not 1 <= self.elites <= self.population:
            raise UserError(
                f"CEM elites must be in [1, population={self.population}], got {self.elites}"
            )
        if self.min_std < 0:
            raise UserError(f"CEM min_std must be >= 0, got {self.min_std}")


@dataclass
class CEMResult:
    """What `CEM.minimize` found, per problem.

    Attributes:
        best: `[B, *shape]` the cheapest candidate seen.
        cost: `[B]` its cost (inf if every candidate cost was NaN / inf).
        mean: `[B, *shape]` the final sampling mean.
        std: `[B, *shape]` the final sampling std.
        iterations: `[B]` int64, iterations run (fewer than the maximum after an early stop).
    """

    best: torch.Tensor
    cost: torch.Tensor
    mean: torch.Tensor
    std: torch.Tensor
    iterations: torch.Tensor


class CEM:
    """Batched CEM minimizer over candidates of any shape (see the module docstring)."""

    def __init__(self, config: CEMConfig):
        self.config = config

    def minimize(
        self,
        cost_fn: CostFn,
        mean: torch.Tensor,
        std: torch.Tensor,
        generators: Sequence[torch.Generator],
    ) -> CEMResult:
        """Minimize `cost_fn` for B problems from initial Gaussians `N(mean, std)`.

        Args:
            cost_fn: Costs of candidate sets `[A, K, *shape]` of the problems `rows [A]`, `[A, K]`.
                NaN counts as +inf.
            mean: `[B, *shape]` initial means (e.g. zeros, or a warm start).
            std: `[B, *shape]` or broadcastable initial stds.
            generators: B generators on `mean.device`, one per problem.

        Returns:
            The best candidate and its cost per problem, and the final Gaussians.
        """
        cfg = self.config
        b, shape = mean.shape[0], tuple(mean.shape[1:])
        if len(generators) != b:
            raise ValueError(f"need one generator per problem: {len(generators)} != {b}")
        mean = mean.clone()
        std = torch.as_tensor(std, dtype=mean.dtype, device=mean.device)
        std = torch.broadcast_to(std, mean.shape).clone()
        best, best_cost = mean.clone(), torch.full((b,), float("inf"), device=mean.device)
        iterations = torch.zeros(b, dtype=torch.long, device=mean.device)
        active = torch.arange(b, device=mean.device)
        for _ in range(cfg.iterations):
            # Sample: each problem from its own generator (batch independence).
            noise = torch.stack(
                [
                    torch.randn(
                        (cfg.population, *shape), generator=generators[i], device=mean.device
                    )
                    for i in active.tolist()
                ]
            )
            x = mean[active, None] + std[active, None] * noise  # [A, K, *shape]
            cost = torch.nan_to_num(cost_fn(x, active), nan=float("inf"))  # [A, K]
            # Keep the best candidate seen.
            c_min, k_min = cost.min(dim=1)
            better = c_min < best_cost[active]
            rows = active[better]
            best[rows] = x[better, k_min[better]]
            best_cost[rows] = c_min[better]
            # Refit the Gaussian to the elites (stable sort: ties resolve the same in any batch).
            order = cost.argsort(dim=1, stable=True)[:, : cfg.elites]
            elites = x[torch.arange(len(active), device=x.device)[:, None], order]  # [A, N, ...]
            mean[active] = elites.mean(dim=1)
            std[active] = elites.std(dim=1, correction=0).clamp_min(cfg.min_std)
            iterations[active] += 1
            if cfg.stop_cost is not None:
                active = active[best_cost[active] >= cfg.stop_cost]
            if active.numel() == 0:
                break
        return CEMResult(best, best_cost, mean, std, iterations)


def problem_generators(seeds: Sequence[int], device: torch.device | str) -> list[torch.Generator]:
    """One `torch.Generator` on `device` per seed."""
    return [torch.Generator(device=device).manual_seed(int(s)) for s in seeds]
