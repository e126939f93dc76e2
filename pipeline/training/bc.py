"""Behaviour cloning of the train split's actions (`pipeline.model.policy`): Adam on the Gaussian
negative log-likelihood, best validation NLL kept.

- `bc`: p(a | s), the LLP baseline's action prior (the paper code's `Prior` over actions).
- `gcbc`: p(a | s, g) with hindsight goals, sampled as OGBench's `GCDataset` does for GCBC
  (`actor_p_trajgoal = 1`, `actor_geom_sample = False`): for step t of an episode whose last step
  is N, the goal is the state at a step drawn uniformly from t + 1 .. N (OGBench:
  `round(min(t + 1, N) * d + N * (1 - d))`, d ~ U[0, 1)), reduced to the goal dims (x, y).
  With `gcbc.normalize: false` it sees raw states, goals and actions, and `gcbc.keep: last` keeps
  the final parameters, as OGBench's GCBC does (results/ogbench-gcbc-check.md: why it matters).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch

from pipeline.config import GCBCParams, PolicyParams
from pipeline.model.policy import GaussianPolicy
from pipeline.model.settings import policy_config
from pipeline.segments import Segments
from pipeline.training.dynamics import split_transitions
from pipeline.training.keep_best import adam_keep_best


def episode_ends(segments: Segments, steps: np.ndarray) -> np.ndarray:
    """Global index of the last step of the episode holding each of `steps [N]`."""
    offsets = segments.episode_offsets
    return offsets[np.searchsorted(offsets, steps, side="right")] - 1


def hindsight_goals(segments: Segments, steps: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Step index `[N]` of one goal per step: uniform over the later steps of its episode
    (OGBench's uniform trajectory goal; the step itself only when it is the episode's last)."""
    last = episode_ends(segments, steps)
    d = rng.random(len(steps))
    return np.round(np.minimum(steps + 1, last) * d + last * (1 - d)).astype(np.int64)


class _Batches:
    """States, actions (and goals) of given steps as tensors on the training device."""

    def __init__(self, segments: Segments, goal_dims: tuple[int, ...], device: torch.device):
        self.segments, self.goal_dims, self.device = segments, list(goal_dims), device
        self.states = torch.as_tensor(segments.states, device=device)
        self.actions = torch.as_tensor(segments.actions, device=device)

    def get(
        self, steps: np.ndarray, rng: np.random.Generator
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        idx = torch.as_tensor(steps, device=self.device)
        goals = None
        if self.goal_dims:
            g = torch.as_tensor(hindsight_goals(self.segments, steps, rng), device=self.device)
            goals = self.states[g][:, self.goal_dims]
        return self.states[idx], self.actions[idx], goals


@torch.no_grad()
def evaluate(policy: GaussianPolicy, s, a, g) -> dict[str, float]:
    """Mean NLL and the RMSE of the mean action (raw units) over given steps `[N, ...]`."""
    mean, _ = policy.action_stats(s, g)
    return {
        "nll": float(policy.nll(s, a, g).mean()),
        "action_rmse": float((mean - a).square().sum(-1).mean().sqrt()),
    }


def fit_policy(
    segments: Segments, cfg: PolicyParams, device: torch.device, goal_dims: tuple[int, ...] = ()
) -> tuple[GaussianPolicy, dict[str, Any]]:
    """Fit p(a | s), or p(a | s, g) with hindsight goals when `goal_dims` is given.

    Adam (`cfg.lr`, `cfg.batch_size` steps drawn uniformly from the train split) for
    `cfg.max_steps`; keeps the parameters with the best validation NLL (every `eval_every` steps
    and at the end, on a fixed subset of `val_transitions` validation steps with fixed goals), or
    the last ones (`GCBCParams.keep`). Inputs and actions are whitened with the train statistics
    unless `GCBCParams.normalize` is false (then the policy works in raw units, as OGBench's).

    Returns:
        The best policy (eval mode) and its metrics: `val_nll`, `val_action_rmse`, `best_step`, ...

    Raises:
        UserError: no train or validation steps, or the loss became NaN/inf.
    """
    rng = np.random.default_rng(cfg.seed)
    train_idx, val_idx = split_transitions(segments, "a policy", cfg.val_transitions, rng)
    torch.manual_seed(cfg.seed)
    info, st = segments.info, segments.stats
    policy = GaussianPolicy(policy_config(cfg, info.state_dim, info.action_dim, goal_dims))
    normalize, keep = True, "best"
    if isinstance(cfg, GCBCParams):
        normalize, keep = cfg.normalize, cfg.keep
    if normalize:  # otherwise the buffers stay mean 0, std 1: raw units, saved as such
        policy.set_normalization(
            {k: getattr(st, k) for k in ("state_mean", "state_std", "action_mean", "action_std")}
        )
    policy.to(device)
    data = _Batches(segments, goal_dims, device)
    val = data.get(val_idx, np.random.default_rng([cfg.seed, 1]))
    started = time.monotonic()

    def next_loss() -> torch.Tensor:
        batch = data.get(train_idx[rng.integers(train_idx.size, size=cfg.batch_size)], rng)
        return policy.nll(*batch).mean()

    metrics, best_step = adam_keep_best(
        policy, policy.net.parameters(), next_loss, lambda: evaluate(policy, *val),
        lr=cfg.lr, max_steps=cfg.max_steps, eval_every=cfg.eval_every, what="policy",
        fix="lower its lr", keep_last=keep == "last",
    )  # fmt: skip
    best: dict[str, Any] = {
        "val_nll": metrics["nll"],
        "val_action_rmse": metrics["action_rmse"],
        "best_step": best_step,
        "steps": cfg.max_steps,
        "train_transitions": int(train_idx.size),
        "goal_conditioned": bool(goal_dims),
        "normalized": normalize,
        "kept": keep,
        "wall_s": time.monotonic() - started,
    }
    return policy.eval(), best
