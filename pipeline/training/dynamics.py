"""Training of the single-step model p(s_{t+1} | s_t, a_t) (`pipeline.model.dynamics`): Adam on
the Gaussian negative log-likelihood of the train split's transitions, best validation NLL kept.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch

from pipeline.config import DynamicsParams
from pipeline.errors import UserError
from pipeline.model.dynamics import DynamicsModel
from pipeline.model.settings import dynamics_config
from pipeline.segments import Segments
from pipeline.training.keep_best import adam_keep_best


def transition_index(segments: Segments, split: str) -> np.ndarray:
    """Global step indices t of `split`'s episodes whose successor t + 1 is in the same episode."""
    offsets = segments.episode_offsets
    parts = [np.arange(offsets[e], offsets[e + 1] - 1) for e in segments.episodes_in(split)]
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


def split_transitions(
    segments: Segments, what: str, val_transitions: int | None, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """The train and validation splits' transitions (`transition_index`), the validation ones a
    fixed random subset of at most `val_transitions` (drawn from `rng`; None: all).

    Raises:
        UserError: a split without transitions (`what` names the model that needs them).
    """
    train_idx = transition_index(segments, "train")
    val_idx = transition_index(segments, "validation")
    if train_idx.size == 0 or val_idx.size == 0:
        raise UserError(f"{what} needs train and validation episodes; see segment.split")
    if val_transitions is not None and val_idx.size > val_transitions:
        val_idx = np.sort(rng.choice(val_idx, val_transitions, replace=False))
    return train_idx, val_idx


def normalization(segments: Segments, train_idx: np.ndarray) -> dict[str, np.ndarray]:
    """Train statistics: the segments' state/action stats plus those of the change s_{t+1} - s_t."""
    delta = segments.states[train_idx + 1].astype(np.float64) - segments.states[train_idx]
    st = segments.stats
    return {
        "state_mean": st.state_mean,
        "state_std": st.state_std,
        "action_mean": st.action_mean,
        "action_std": st.action_std,
        "delta_mean": delta.mean(0),
        "delta_std": np.maximum(delta.std(0), 1e-8),
    }


def _transitions(segments: Segments, idx: np.ndarray, device: torch.device) -> tuple:
    return tuple(
        torch.as_tensor(x, dtype=torch.float32, device=device)
        for x in (segments.states[idx], segments.actions[idx], segments.states[idx + 1])
    )


@torch.no_grad()
def evaluate(model: DynamicsModel, s, a, s_next) -> dict[str, float]:
    """Mean NLL and one-step position/state RMSE (raw units) over given transitions `[N, ...]`."""
    mean, _ = model.predict(s, a)
    return {
        "nll": float(model.nll(s, a, s_next).mean()),
        "rmse": float((mean - s_next).square().sum(-1).mean().sqrt()),
    }


def fit_dynamics(
    segments: Segments, cfg: DynamicsParams, device: torch.device
) -> tuple[DynamicsModel, dict[str, float]]:
    """Train a `DynamicsModel` (`cfg.hidden`, `cfg.min_std`) on train-split transitions by Adam
    on the Gaussian NLL.

    Keeps the parameters with the best validation NLL (evaluated every `eval_every` steps on a
    fixed subset of `val_transitions` validation-split transitions, and at the end).

    Returns:
        The best model (eval mode) and its metrics: `val_nll`, `val_rmse`, `best_step`, ...

    Raises:
        UserError: no train or validation transitions, or the loss became NaN/inf.
    """
    rng = np.random.default_rng(cfg.seed)
    train_idx, val_idx = split_transitions(segments, "the dynamics model", cfg.val_transitions, rng)
    torch.manual_seed(cfg.seed)
    info = segments.info
    model = DynamicsModel(dynamics_config(cfg, info.state_dim, info.action_dim))
    model.set_normalization(normalization(segments, train_idx))
    model.to(device)
    train, val = _transitions(segments, train_idx, device), _transitions(segments, val_idx, device)
    generator = torch.Generator().manual_seed(cfg.seed)
    started = time.monotonic()

    def next_loss() -> torch.Tensor:
        batch = torch.randint(train_idx.size, (cfg.batch_size,), generator=generator).to(device)
        return model.nll(*(x[batch] for x in train)).mean()

    metrics, best_step = adam_keep_best(
        model, model.net.parameters(), next_loss, lambda: evaluate(model, *val),
        lr=cfg.lr, max_steps=cfg.max_steps, eval_every=cfg.eval_every, what="dynamics",
        fix="lower dynamics.lr",
    )  # fmt: skip
    best: dict[str, Any] = {
        "val_nll": metrics["nll"],
        "val_rmse": metrics["rmse"],
        "best_step": best_step,
        "steps": cfg.max_steps,
        "train_transitions": int(train_idx.size),
        "wall_s": time.monotonic() - started,
    }
    return model.eval(), best
