"""A batched cross-entropy method (Rubinstein, 1999) that knows nothing about the world model.

`CEM.minimize` solves B independent problems at once. Each problem keeps a diagonal Gaussian over
a candidate of any shape; every iteration samples K candidates per problem, asks the cost function
for all of them in one call (`[B, K, *shape] -> [B, K]`), and refits the Gaussian to the N_keep
cheapest (paper appendix C.6). The best candidate seen is returned, with whatever the cost function
computed along with its cost (e.g. the predicted states), so nothing is evaluated twice.

Shapes never change inside a plan and nothing is read back to the host: problems whose best cost
falls under `stop_cost` (the paper's threshold, §4.2 footnote 1) are marked done and frozen, not
removed, so one iteration (`CEM.step`) is a pure tensor function that `torch.compile` and CUDA
graphs can take whole. Each problem draws its noise from its own counter-based stream
(`pipeline.planning.noise`, keyed by the problem's key and the iteration), so a problem's result
does not depend on which other problems share the batch (tests/test_planning.py checks this).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch

from pipeline.errors import UserError
from pipeline.planning.noise import normal, substream

# `candidates [B, K, *shape] -> (cost [B, K], extras)`: `extras` is a tuple of `[B, K, ...]`
# tensors computed with the cost (e.g. predicted states); CEM keeps the best candidate's.
CostFn = Callable[[torch.Tensor], tuple[torch.Tensor, tuple[torch.Tensor, ...]]]
# `(state, cost_fn, iteration keys [B]) -> state`: `CEM.step`, or a compiled version of it.
StepFn = Callable[["CEMState", CostFn, torch.Tensor], "CEMState"]


@dataclass(frozen=True)
class CEMConfig:
    """CEM settings (paper table 14 names in brackets). No defaults: the params models
    (`pipeline.config`) hold them, and `pipeline.planning.settings` builds this from them.

    Attributes:
        candidates: Candidates sampled per problem and iteration [K] (`deploy.planner.candidates`,
            `deploy.llp.candidates`).
        elites: Cheapest candidates the Gaussian is refit to [N_keep].
        iterations: Maximum iterations [N_iters].
        min_std: Floor on the refit std, so the search never collapses to a point.
        stop_cost: Stop a problem once its best cost is below this; None: run all iterations.
    """

    candidates: int
    elites: int
    iterations: int
    min_std: float
    stop_cost: float | None

    def __post_init__(self) -> None:
        if self.candidates < 1 or self.iterations < 1:
            raise UserError(
                f"CEM needs candidates >= 1 and iterations >= 1, got {self.candidates}, "
                f"{self.iterations}"
            )
        if not 1 <= self.elites <= self.candidates:
            raise UserError(
                f"CEM elites must be in [1, candidates={self.candidates}], got {self.elites}"
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
        extras: The best candidate's extras from the cost function, each `[B, ...]`.
    """

    best: torch.Tensor
    cost: torch.Tensor
    mean: torch.Tensor
    std: torch.Tensor
    iterations: torch.Tensor
    extras: tuple[torch.Tensor, ...] = ()


class CEMState(NamedTuple):
    """The search state between iterations; all `[B, ...]`, fixed shapes.

    `best_extras` is None before the first iteration (the first iteration's cheapest sample
    becomes the best, whatever its cost, so the extras always belong to a sampled candidate).
    """

    mean: torch.Tensor
    std: torch.Tensor
    best: torch.Tensor
    best_cost: torch.Tensor
    best_extras: tuple[torch.Tensor, ...] | None
    iterations: torch.Tensor
    done: torch.Tensor


class CEM:
    """Batched CEM minimizer over candidates of any shape (see the module docstring)."""

    def __init__(self, config: CEMConfig):
        self.config = config

    def init(self, mean: torch.Tensor, std: torch.Tensor | float) -> CEMState:
        """The state before the first iteration: `N(mean [B, *shape], std)` (std broadcast)."""
        if isinstance(std, torch.Tensor):
            std = torch.broadcast_to(std.to(mean), mean.shape).clone()
        else:  # no host-to-device copy: a CUDA graph may be capturing
            std = torch.full_like(mean, float(std))
        b = mean.shape[0]
        return CEMState(
            mean=mean.clone(),
            std=std,
            best=mean.clone(),
            best_cost=torch.full((b,), float("inf"), device=mean.device),
            best_extras=None,
            iterations=torch.zeros(b, dtype=torch.long, device=mean.device),
            done=torch.zeros(b, dtype=torch.bool, device=mean.device),
        )

    def step(self, state: CEMState, cost_fn: CostFn, keys: torch.Tensor) -> CEMState:
        """One iteration for all B problems; problems already done keep their state.

        Args:
            state: The state after the previous iteration (`init` before the first).
            cost_fn: Costs (NaN counts as +inf) and extras of candidates `[B, K, *shape]`.
            keys: `[B]` this iteration's stream keys (`noise.substream(problem keys, i)`).
        """
        cfg = self.config
        b, shape = state.mean.shape[0], state.mean.shape[1:]
        # Sample: each problem from its own stream.
        noise = normal(keys, (cfg.candidates, *shape))
        x = state.mean[:, None] + state.std[:, None] * noise  # [B, K, *shape]
        cost, extras = cost_fn(x)
        cost = torch.nan_to_num(cost, nan=float("inf"))  # [B, K]
        # Elites: the N_keep cheapest, cheapest first (a partial sort: topk, not argsort). The
        # cheapest is read off them: torch 2.11's inductor returns wrong argmin indices when it
        # fuses the argmin with the cost's own reduction (tests/test_planning.py compiles this).
        top = cost.topk(cfg.elites, dim=1, largest=False, sorted=True)  # [B, N]
        c_min, k_min = top.values[:, 0], top.indices[:, 0]
        # Keep the best candidate seen (and what the cost function computed with it).
        x_min = _pick(x, k_min)
        extras_min = tuple(_pick(e, k_min) for e in extras)
        live = ~state.done
        if state.best_extras is None:  # first iteration
            best, best_cost, best_extras = x_min, c_min, extras_min
        else:
            better = (c_min < state.best_cost) & live
            best = _where(better, x_min, state.best)
            best_cost = torch.where(better, c_min, state.best_cost)
            best_extras = tuple(
                _where(better, new, old)
                for new, old in zip(extras_min, state.best_extras, strict=True)
            )
        # Refit the Gaussian to the elites.
        order = top.indices.view(b, cfg.elites, *[1] * len(shape))
        elites = torch.take_along_dim(x, order, dim=1)
        mean = _where(live, elites.mean(dim=1), state.mean)
        std = _where(live, elites.std(dim=1, correction=0).clamp_min(cfg.min_std), state.std)
        done = state.done
        if cfg.stop_cost is not None:
            done = done | (best_cost < cfg.stop_cost)
        return CEMState(
            mean, std, best, best_cost, best_extras, state.iterations + live.long(), done
        )

    def minimize(
        self,
        cost_fn: CostFn,
        mean: torch.Tensor,
        std: torch.Tensor | float,
        keys: torch.Tensor,
        step: StepFn | None = None,
    ) -> CEMResult:
        """Minimize `cost_fn` for B problems from initial Gaussians `N(mean, std)`.

        Args:
            cost_fn: Costs (NaN counts as +inf) and extras of candidates `[B, K, *shape]`.
            mean: `[B, *shape]` initial means (e.g. zeros, or a warm start).
            std: `[B, *shape]` or broadcastable initial stds.
            keys: `[B]` int64 stream keys, one per problem (`noise.problem_keys`).
            step: What runs one iteration (default `self.step`; e.g. a compiled version of it).

        Returns:
            The best candidate, its cost and extras per problem, and the final Gaussians.
        """
        if keys.shape != mean.shape[:1]:
            raise ValueError(f"need one key per problem: {tuple(keys.shape)} vs {mean.shape[0]}")
        step = step or self.step
        state = self.init(mean, std)
        # On CPU a flag costs no device synchronization: stop as soon as every problem is done.
        stop_early = self.config.stop_cost is not None and mean.device.type == "cpu"
        for i in range(self.config.iterations):
            state = step(state, cost_fn, substream(keys, i))
            if stop_early and bool(state.done.all()):
                break
        return result_of(state)


def result_of(state: CEMState) -> CEMResult:
    """The `CEMResult` of a search state."""
    return CEMResult(
        state.best, state.best_cost, state.mean, state.std, state.iterations, state.best_extras
    )


def _pick(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """`x[b, index[b]]` for `x [B, K, ...]`, `index [B]` -> `[B, ...]`."""
    shaped = index.view(-1, 1, *[1] * (x.dim() - 2))
    return torch.take_along_dim(x, shaped, dim=1)[:, 0]


def _where(mask: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Row-wise select: `a[i]` where `mask [B]`, else `b[i]`."""
    return torch.where(mask.view(-1, *[1] * (a.dim() - 1)), a, b)
