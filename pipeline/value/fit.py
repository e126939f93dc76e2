"""Fitting V(s, g) offline: implicit value learning (GCIVL, OGBench's recipe) on the train split.

For a train transition (s, s') and a goal g drawn as OGBench's value goals are (the step itself
with `p_current`, a later step of the same episode `k ~ Geometric(1 - discount)` ahead with
`p_trajectory`, any train step with the rest), the reward is 0 where s already reaches g by the
environment's own success rule and -1 otherwise, and the episode ends there. Each head i regresses
on `q_i = r + discount * (1 - reached) * V'_i(s', g)` with the expectile loss
`|expectile - 1(adv < 0)| * (q_i - V_i)^2`, where `adv` compares the heads' pessimistic target
`r + discount * (1 - reached) * min_i V'_i(s', g)` with the target heads' mean at s: an in-sample
maximum over the data's behaviour, with no policy and no action. The target network follows by
Polyak averaging (`tau`). The final parameters are kept (as OGBench evaluates).

Validation measures what the planner uses: on held-out episodes, for goals `k` steps ahead
(uniform up to `eval_horizon`), the predicted steps to go against the steps the recorded episode
actually took to reach the goal (its first step within the success rule).
"""

from __future__ import annotations

import copy
import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from scipy.stats import spearmanr

from pipeline.config import ValueParams
from pipeline.errors import UserError
from pipeline.segments import Segments
from pipeline.training.bc import episode_ends
from pipeline.training.dynamics import split_transitions
from pipeline.value.network import GoalValue, ValueConfig

log = logging.getLogger(__name__)

# `(states [N, sd], goals [N, G]) -> bool [N]`: the environment's success rule on observations.
Reached = Callable[[np.ndarray, np.ndarray], np.ndarray]


def value_goals(
    segments: Segments,
    steps: np.ndarray,
    pool: np.ndarray,
    cfg: ValueParams,
    rng: np.random.Generator,
) -> np.ndarray:
    """Step index `[N]` of one goal per step of `steps [N]` (module docstring); `pool`: the steps
    random goals are drawn from."""
    n = len(steps)
    last = episode_ends(segments, steps)
    ahead = np.minimum(steps + rng.geometric(1 - cfg.discount, size=n), last)
    anywhere = pool[rng.integers(pool.size, size=n)]
    u = rng.random(n)
    cut = cfg.p_current + cfg.p_trajectory
    return np.where(u < cfg.p_current, steps, np.where(u < cut, ahead, anywhere))


def expectile_loss(adv: torch.Tensor, diff: torch.Tensor, expectile: float) -> torch.Tensor:
    """`|expectile - 1(adv < 0)| * diff^2`, elementwise."""
    weight = torch.where(adv < 0, 1 - expectile, expectile)
    return weight * diff.square()


def _td_loss(
    value: GoalValue, target: GoalValue, batch: tuple[torch.Tensor, ...], cfg: ValueParams
) -> torch.Tensor:
    """The heads' summed expectile loss on one batch (module docstring)."""
    s, s_next, g, done = batch
    with torch.no_grad():
        next_v = target.heads_values(s_next, g)  # [N, heads]
        keep = cfg.discount * (1 - done)[:, None]
        q = (done - 1)[:, None] + keep * next_v  # [N, heads]
        q_min = (done - 1) + keep[:, 0] * next_v.amin(-1)
        adv = q_min - target.heads_values(s, g).mean(-1)
    v = value.heads_values(s, g)
    return expectile_loss(adv[:, None], q - v, cfg.expectile).mean(0).sum()


class _Data:
    """Transitions of given steps with value goals, as tensors on the training device."""

    def __init__(self, segments: Segments, goal_dims, reached: Reached, cfg: ValueParams, device):
        self.segments, self.dims, self.reached, self.cfg = segments, list(goal_dims), reached, cfg
        self.device = device

    def batch(self, steps: np.ndarray, pool: np.ndarray, rng: np.random.Generator):
        states = self.segments.states
        goals = states[value_goals(self.segments, steps, pool, self.cfg, rng)][:, self.dims]
        done = np.asarray(self.reached(states[steps], goals), dtype=np.float32)
        return tuple(
            torch.as_tensor(x, device=self.device)
            for x in (states[steps], states[steps + 1], goals, done)
        )


def distance_samples(
    segments: Segments,
    steps: np.ndarray,
    goal_dims,
    reached: Reached,
    horizon: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Held-out (step, goal, steps the record took to reach it): for each of `steps [N]` the goal
    is the state `k ~ U{1..horizon}` steps later (within its episode), and the record reached it
    at its first step within the success rule (at most k)."""
    last = episode_ends(segments, steps)
    target = np.minimum(steps + rng.integers(1, horizon + 1, size=len(steps)), last)
    goals = segments.states[target][:, list(goal_dims)]
    took = target - steps
    for j in range(int(took.max()) + 1):  # earliest hit first: scan forward, keep the first
        still = took > j
        if not still.any():
            break
        hit = np.zeros(len(steps), dtype=bool)
        idx = np.flatnonzero(still)
        hit[idx] = reached(segments.states[steps[idx] + j], goals[idx])
        took = np.where(hit, j, took)
    return steps, goals, took


@torch.no_grad()
def evaluate(value: GoalValue, segments: Segments, samples, data: _Data, loss_batch, cfg):
    """Validation: the TD loss on a fixed batch, and predicted steps to go against the record."""
    steps, goals, took = samples
    device = value.state_mean.device
    s = torch.as_tensor(segments.states[steps], device=device)
    predicted = value.steps_to_go(s, torch.as_tensor(goals, device=device)).cpu().numpy()
    defined = np.ptp(took) > 0 and np.ptp(predicted) > 0  # else no rank correlation
    rho = float(spearmanr(predicted, took).statistic) if defined else None
    return {
        "td_loss": float(_td_loss(value, value, loss_batch, cfg)),
        "steps_to_go_mae": float(np.abs(predicted - took).mean()),
        "steps_to_go_spearman": rho,
        "recorded_steps_to_go_mean": float(took.mean()),
    }


def spearman_text(x: float | None) -> str:
    """A rank correlation for logs: 3 decimals, or "undefined"."""
    return "undefined" if x is None else f"{x:.3f}"


def fit_value(
    segments: Segments,
    cfg: ValueParams,
    device: torch.device,
    goal_dims: tuple[int, ...],
    reached: Reached,
) -> tuple[GoalValue, dict[str, Any]]:
    """Fit V(s, g) on the train split (module docstring); validate on the validation split.

    Returns:
        The value network (eval mode, the final parameters) and its metrics.

    Raises:
        UserError: no train or validation transitions, or the loss became NaN/inf.
    """
    rng = np.random.default_rng(cfg.seed)
    train_idx, val_idx = split_transitions(segments, "a value", None, rng)
    torch.manual_seed(cfg.seed)
    config = ValueConfig(
        segments.info.state_dim, goal_dims, cfg.hidden, cfg.layers, cfg.heads, cfg.discount
    )
    value = GoalValue(config)
    value.set_normalization(segments.stats.state_mean, segments.stats.state_std)
    value.to(device)
    target = copy.deepcopy(value).requires_grad_(False)
    data = _Data(segments, goal_dims, reached, cfg, device)
    val_rng = np.random.default_rng([cfg.seed, 1])
    val_steps = np.sort(val_rng.choice(val_idx, min(cfg.val_transitions, val_idx.size), False))
    val_batch = data.batch(val_steps, val_idx, val_rng)
    samples = distance_samples(segments, val_steps, goal_dims, reached, cfg.eval_horizon, val_rng)
    optimizer = torch.optim.Adam(value.parameters(), lr=cfg.lr)
    history = []
    started = time.monotonic()
    for step in range(1, cfg.max_steps + 1):
        steps = train_idx[rng.integers(train_idx.size, size=cfg.batch_size)]
        loss = _td_loss(value, target, data.batch(steps, train_idx, rng), cfg)
        if not torch.isfinite(loss):
            raise UserError(f"value training diverged at step {step}; lower value.lr")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        with torch.no_grad():
            for p, p_target in zip(value.parameters(), target.parameters(), strict=True):
                p_target.lerp_(p, cfg.tau)
        if step % cfg.eval_every == 0 or step == cfg.max_steps:
            metrics = evaluate(value.eval(), segments, samples, data, val_batch, cfg)
            value.train()
            history.append({"step": step, **metrics})
            log.info(
                "value step %d: val TD loss %.4f, steps to go MAE %.1f (Spearman %s)",
                step, metrics["td_loss"], metrics["steps_to_go_mae"],
                spearman_text(metrics["steps_to_go_spearman"]),
            )  # fmt: skip
    final = history[-1]
    return value.eval(), {
        **{f"val_{k}": v for k, v in final.items() if k != "step"},
        "steps": cfg.max_steps,
        "train_transitions": int(train_idx.size),
        "history": history,
        "wall_s": time.monotonic() - started,
    }
